"""Power-cut crash states of real recordings, explored: ``python tests/crash_states/sweep.py``.

Captures one real recording (a container under strace with a camera, an IMU and one recorder per
configuration: MCAP and SQLite3, split and unsplit, default flush and sync intervals), then, per configuration,
draws seeded crash states of its bag under the ext4 ``data=ordered`` model of ``model.py``, materializes each as a
directory, runs ``bag recover`` in place, reads the result with rosbags, the mcap reader or sqlite3 and
``bag info``, and checks it against the finished recording (``oracle.py``). Prints every failing state with its
seed and what was kept, dropped and torn, and a summary per configuration. Exit status 1 if any state failed.

    python tests/crash_states/sweep.py --states 1000                      # capture, then 1000 states each
    python tests/crash_states/sweep.py --capture-dir /tmp/pc --states 1000  # reuse (or make) a capture there
    python tests/crash_states/sweep.py --capture-dir /tmp/pc --config sqlite3 --replay 1234   # one seed

See docs/design/power-cut.md.
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import os
import pickle
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: the tests directory and the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    sys.path.insert(1, str(Path(__file__).resolve().parents[2]))

from crash_states.capture import CONFIGS, Capture, Config, capture, strace_usable  # noqa: E402
from crash_states.model import MODELS, BagModel  # noqa: E402
from crash_states.oracle import (Outcome, Reference, Visibility, check_state, read_reference,  # noqa: E402
                                 visibility)
from crash_states.strace_log import Trace, parse_trace  # noqa: E402

SYNC_INTERVAL = 1.0  # the recorder's default storage.sync_interval, which the capture uses
SLACK = 0.5  # the writer checks the sync deadline at least every 0.2 s; plus one fsync


@dataclasses.dataclass
class Prepared:
    """A configuration ready for crash states: its model, reference and SIGKILL visibility."""

    config: Config
    model: BagModel
    reference: Reference
    seen: Visibility


@dataclasses.dataclass
class Summary:
    config: str
    model: str
    states: int = 0
    failures: int = 0
    seconds: float = 0.0
    failing_seeds: list[int] = dataclasses.field(default_factory=list)
    kinds: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    bag_missing: int = 0
    required_sync: int = 0
    required_fsync: int = 0
    oldest_lost_age: float = 0.0
    lost_states: int = 0

    def line(self) -> str:
        text = (f"{self.config} [{self.model}]: {self.states} states, {self.failures} failed, "
                f"{self.seconds:.1f} s; bag directory absent in {self.bag_missing}; messages required per state "
                f"(sync bound / fsync) {self.required_sync / max(1, self.states):.0f} / "
                f"{self.required_fsync / max(1, self.states):.0f}; oldest message lost (by receive time) "
                f"{self.oldest_lost_age:.2f} s before the cut")
        if self.failures:
            text += f"\n    failure kinds: {dict(self.kinds)}\n    failing seeds: {self.failing_seeds[:20]}"
        return text


def load_capture(directory: Path, configs: list[Config], seconds: float, camera: tuple[int, int],
                 log=print) -> tuple[Capture, Trace]:
    """Capture into ``directory`` unless it already holds a capture (then reuse it and its parsed trace)."""
    facts = directory / "capture.json"
    parsed = directory / "trace.pickle"
    if facts.exists():
        data = json.loads(facts.read_text())
        made = Capture(Path(data["workdir"]), Path(data["log"]), Path(data["root"]),
                       [CONFIGS[name] for name in data["configs"]], data["seconds"], data["wall"],
                       tuple(data["camera"]), data["exit_code"])
        log(f"reusing the capture in {directory} ({', '.join(c.name for c in made.configs)})")
    else:
        made = capture(directory, configs, seconds=seconds, camera=camera)
        log(f"captured {seconds} s of recording ({', '.join(c.name for c in configs)}) in {made.wall:.1f} s, "
            f"container exit {made.exit_code}; log {made.log.stat().st_size / 1e6:.0f} MB")
        if made.exit_code != 0:
            raise RuntimeError(f"the traced container exited with {made.exit_code}: see {directory}/container.log")
        facts.write_text(json.dumps({
            "workdir": str(made.workdir), "log": str(made.log), "root": str(made.root),
            "configs": [c.name for c in made.configs], "seconds": made.seconds, "wall": made.wall,
            "camera": list(made.camera), "exit_code": made.exit_code}))
    if parsed.exists():
        with open(parsed, "rb") as stream:
            trace = pickle.load(stream)
    else:
        started = time.monotonic()
        trace = parse_trace(made.log, made.root, made.workdir)
        with open(parsed, "wb") as stream:
            pickle.dump(trace, stream, protocol=pickle.HIGHEST_PROTOCOL)
        log(f"parsed {trace.lines} lines into {len(trace.ops)} operations in {time.monotonic() - started:.1f} s")
    return made, trace


def prepare(made: Capture, trace: Trace, config: Config, model_name: str, scratch: Path, log=print) -> Prepared:
    """Model the bag, read its reference, check the trace reproduces it, find when each message was written."""
    started = time.monotonic()
    model = BagModel(trace, config.name, model_name)
    bag = made.bag(config)
    reference = read_reference(bag)
    final = model.sigkill_state(model.last_line + 1)  # every operation applied: must be the bag on disk
    on_disk = {path.name: path.read_bytes() for path in bag.iterdir()}
    if final.files != on_disk:
        differ = sorted(name for name in set(final.files) | set(on_disk)
                        if final.files.get(name) != on_disk.get(name))
        raise RuntimeError(f"{config.name}: replaying the trace does not give the recorded bag: {differ}")
    seen = visibility(model, reference, config.storage_id, scratch / f"visibility_{config.name}")
    if seen.never or seen.non_monotonic:
        raise RuntimeError(f"{config.name}: {len(seen.never)} messages never visible after a SIGKILL, "
                           f"{seen.non_monotonic} visible and later gone")
    log(f"{config.name}: {len(model.ops)} operations, {len(reference.messages)} messages, the trace replays to "
        f"the recorded bag byte for byte; when each message was written: {seen.evaluations} SIGKILL states, "
        f"{time.monotonic() - started:.1f} s")
    return Prepared(config, model, reference, seen)


def explore(prepared: Prepared, seeds: list[int], scratch: Path, log=print, keep: Path | None = None,
            verbose: bool = False) -> Summary:
    """Draw, check and report the crash state of every seed."""
    summary = Summary(prepared.config.name, prepared.model.model)
    started = time.monotonic()
    for seed in seeds:
        rng = random.Random(f"{prepared.config.name}:{seed}")
        state = prepared.model.draw(rng)
        directory = scratch / f"state_{prepared.config.name}" / prepared.config.name
        shutil.rmtree(directory.parent, ignore_errors=True)
        directory.parent.mkdir(parents=True)
        outcome: Outcome = check_state(prepared.model, state, prepared.reference, prepared.seen,
                                       prepared.config.storage_id, directory, SYNC_INTERVAL, SLACK)
        summary.states += 1
        summary.bag_missing += not state.bag_exists
        summary.required_sync += outcome.required_sync
        summary.required_fsync += outcome.required_fsync
        summary.oldest_lost_age = max(summary.oldest_lost_age, outcome.oldest_lost_age)
        if outcome.failures:
            summary.failures += 1
            summary.failing_seeds.append(seed)
            for failure in outcome.failures:
                summary.kinds[_kind(failure)] += 1
            log(f"FAILED POWER_CUT_SEED={seed} config={prepared.config.name} model={prepared.model.model}: "
                f"{len(outcome.failures)} failures")
            for failure in outcome.failures:
                log(f"  - {failure}")
            log(_indent(state.describe(), "    "))
            if outcome.recovered:
                log(_indent(outcome.recovered, "    recover: "))
            if keep is not None:
                target = keep / f"{prepared.config.name}_{seed}"
                shutil.rmtree(target, ignore_errors=True)
                state.materialize(target / prepared.config.name)
        elif verbose:
            log(f"ok POWER_CUT_SEED={seed} config={prepared.config.name}: {outcome.present} messages, required "
                f"{outcome.required_sync}/{outcome.required_fsync}")
        shutil.rmtree(directory.parent, ignore_errors=True)
    summary.seconds = time.monotonic() - started
    return summary


def _kind(failure: str) -> str:
    for marker, kind in (("sync_interval", "sync bound"), ("completed fsync", "fsync durability"),
                         ("corrupted", "corrupted"), ("twice", "duplicate"), ("disagree", "readers disagree"),
                         ("bag info", "bag info"), ("raised", "recover raised"), ("had not begun", "from the future")):
        if marker in failure:
            return kind
    return failure.split(":")[0][:40]


def _indent(text: str, prefix: str) -> str:
    lines = text.splitlines()
    if len(lines) > 40:
        lines = lines[:40] + [f"... ({len(lines) - 40} more lines)"]
    return "\n".join(prefix + line for line in lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--states", type=int, default=1000, help="crash states per configuration (default 1000)")
    parser.add_argument("--seed", type=int, default=0, help="first seed (states use seed, seed+1, ...)")
    parser.add_argument("--replay", type=int, action="append", default=[], metavar="SEED",
                        help="check only these seeds (repeatable), printing each state")
    parser.add_argument("--config", action="append", choices=sorted(CONFIGS), default=[],
                        help="configurations (repeatable; default all four)")
    parser.add_argument("--model", choices=MODELS, action="append", default=[],
                        help="persistence model: strict (default: directory entries durable by a directory "
                             "fsync only) or ext4 (any fsync commits the journal); repeatable")
    parser.add_argument("--capture-dir", type=Path, help="reuse the capture there, or capture into it")
    parser.add_argument("--seconds", type=float, default=4.0, help="recording length of a new capture")
    parser.add_argument("--camera", default="128x96", help="camera frame size of a new capture (WxH)")
    parser.add_argument("--keep-failures", type=Path, help="materialize every failing state there")
    parser.add_argument("--verbose", action="store_true", help="one line for every state")
    args = parser.parse_args(argv)
    configs = [CONFIGS[name] for name in (args.config or list(CONFIGS))]
    models = args.model or ["strict"]
    unusable = strace_usable()
    if unusable:
        print(f"cannot capture: {unusable}", file=sys.stderr)
        return 2
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(150, 230)))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    scratch = Path(tempfile.mkdtemp(prefix="power_cut_", dir="/dev/shm" if Path("/dev/shm").is_dir() else None))
    # The recording itself goes to the ordinary disk (/tmp here: ext4), the crash states to tmpfs.
    capture_dir = args.capture_dir or Path(tempfile.mkdtemp(prefix="power_cut_capture_"))
    width, height = (int(v) for v in args.camera.lower().split("x"))
    started = time.monotonic()
    try:
        made, trace = load_capture(capture_dir, configs, args.seconds, (width, height))
        missing = [c.name for c in configs if c not in made.configs]
        if missing:
            print(f"the capture in {capture_dir} has no {missing}", file=sys.stderr)
            return 2
        summaries = []
        seeds = args.replay or list(range(args.seed, args.seed + args.states))
        for config in configs:
            for model_name in models:
                prepared = prepare(made, trace, config, model_name, scratch)
                summaries.append(explore(prepared, seeds, scratch, keep=args.keep_failures,
                                         verbose=args.verbose or bool(args.replay)))
                print(summaries[-1].line(), flush=True)
        print(f"\n{sum(s.states for s in summaries)} crash states tried, {sum(s.failures for s in summaries)} "
              f"failed, {time.monotonic() - started:.0f} s in all")
        for summary in summaries:
            print("  " + summary.line())
        return 1 if any(s.failures for s in summaries) else 0
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        if args.capture_dir is None:
            shutil.rmtree(capture_dir, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
