"""The soak benchmark (``benchmarks/soak.py``): one container recording the S1 rig for a long time while
components come and go.

* ``plan``: the run's shape (durations, periods, the rig, the components' load requests);
* ``churn``: the run itself: the container, the extra driver every few seconds, the recorder handed over every
  minute, the player, the samples of the container's resources, the bag files collected as they close;
* ``bag_files``: one storage file read by ``baglib`` and by ``rosbags`` (in a worker process): what it holds;
* ``accounting``: every sequence number of every stream accounted for in the union of the bags;
* ``resources``: RSS, open file descriptors and threads of the container: fitted slopes and bounds;
* ``main``: the command line, the report and the result folder.

benchmarks/README.md says what is measured and how it is judged.
"""
