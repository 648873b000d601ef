"""The recording benchmark (run by benchmarks/record_bench.py): the recorder in the drivers' container,
intra-process, against the same recorder in a process of its own over DDS, on the same scenarios.

* :mod:`~benchmarks.record.scenarios`: S1 (multi-camera rig), S2 (camera ramp), S3 (IMU storm);
* :mod:`~benchmarks.record.modes`: one measured run of a mode (ipc, split, dds, drivers only, baseline);
* :mod:`~benchmarks.record.disk`: the buffered ceiling and the direct-write limit of the bags' disk;
* :mod:`~benchmarks.record.measure`, :mod:`~benchmarks.record.bag_count`: what a run measures (CPU from /proc,
  the bag read back and counted);
* :mod:`~benchmarks.record.figures`, :mod:`~benchmarks.record.targets`: derived figures and the pass/fail
  targets, ratios of figures measured side by side in the same run;
* :mod:`~benchmarks.record.report`: the text report; :mod:`~benchmarks.record.main`: the command line.
"""
