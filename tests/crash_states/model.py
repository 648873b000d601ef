"""Crash states of a traced bag after a power cut, in the manner of ALICE and CrashMonkey.

A *crash state* is what the disk holds after the power fails at a *cut*: a point between two lines of the
trace. It is built from the bag's operations (``trace.Op``) under a persistence model of ext4 with
``data=ordered`` (the default mount option), stated in docs/design/power-cut.md and implemented here:

Operations. At the cut an operation is *done* (its exit line is before the cut), *in flight* (entered, not
returned: it may or may not have reached the page cache, so it is treated like a done one that is not
durable) or *future* (never happened). Future operations are never in a crash state.

Durable. ``fsync``/``fdatasync`` of a file that returned before the cut makes durable every data operation
(write, truncate) on that file that returned before the fsync was entered: its bytes and its size. An fsync
of a directory that returned before the cut makes durable every entry operation in that directory (create,
mkdir, unlink, rename) that returned before it was entered. ``sync``/``syncfs`` makes everything durable.
(Model ``ext4``, more lenient and closer to jbd2: any completed fsync, of any file or directory of the bag,
commits the journal and so makes every entry operation before it durable.)

Not durable (after the last such fsync), per the model:

* *entry operations of a directory* persist as a prefix, in order: the first k of them, k from 0 to all. A
  rename is one operation, so it is atomic. A file whose create is not in the prefix is not there (its data
  is orphaned); a directory whose mkdir is not there is not there, nor is anything below it;
* *the size of a file* persists as a prefix of its size changes (appending writes and truncates) after the
  durable size: the size after the first k of its pending data operations, k from 0 to all (i_disksize is
  journaled metadata, updated in order);
* *the contents* are chosen per 4 KiB block: each block holds its durable content or its content after any
  one of the pending writes that touched it (writeback of dirty pages is in any order, but a block is
  written whole: it reflects the file at one moment). Where the persisted size covers bytes an appending
  write added (the size grew over them with that write), the block holds at least that write's version:
  ``data=ordered`` writes the data of the new extent before it commits the size that exposes it, so an
  append whose size update persisted has its data (no stale data, no zeros). Bytes within the size that no
  chosen version wrote read as zeros (an unwritten or hole block);
* ``O_DIRECT`` writes are treated like buffered ones (the device's volatile write cache can lose them until a
  flush, which is what fsync sends).

The sampler draws each state from a seed: the cut, then for every directory and every file a mode: all of the
non-durable operations kept (what a SIGKILL leaves), none of them (only what was made durable), a prefix
torn at a 4 KiB block (the ops before it kept, the op at the tear kept for its first blocks), or a random
choice (a random size prefix and a random version per block, within the constraints above).
"""
from __future__ import annotations

import bisect
import dataclasses
import random
from pathlib import Path

from .strace_log import ROOT, Op, Trace

BLOCK = 4096
MODES = ("all", "none", "prefix", "random")
MODELS = ("strict", "ext4")


@dataclasses.dataclass
class FileState:
    """How one file of a crash state was made (for reports)."""

    name: str
    ino: int
    durable_ops: int
    pending: list[Op]
    mode: str
    size_prefix: int  # how many pending data operations' size changes persisted
    size: int
    versions: dict[int, int]  # block -> number of pending writes applied to it (only blocks that differ)
    blocks: int  # blocks touched by pending writes

    def describe(self) -> str:
        if not self.pending:
            return f"{self.name}: durable, {self.size} bytes"
        full = sum(1 for version in self.versions.values() if version == len(self.pending))
        none = sum(1 for version in self.versions.values() if version == 0)
        return (f"{self.name}: {self.durable_ops} durable data ops, {len(self.pending)} pending "
                f"({self.pending[0].describe()} .. {self.pending[-1].describe()}); mode {self.mode}: size after "
                f"{self.size_prefix} of them = {self.size} bytes; of {self.blocks} dirty blocks {full} newest, "
                f"{none} durable, {self.blocks - full - none} older versions")


@dataclasses.dataclass
class DirState:
    path: str
    durable: int
    pending: list[Op]
    kept: int
    mode: str

    def describe(self) -> str:
        if not self.pending:
            return f"dir {self.path or '.'}: {self.durable} entry ops, all durable"
        kept = ", ".join(op.describe() for op in self.pending[:self.kept]) or "none"
        dropped = ", ".join(op.describe() for op in self.pending[self.kept:]) or "none"
        return (f"dir {self.path or '.'}: {self.durable} entry ops durable, {len(self.pending)} not (mode "
                f"{self.mode}); kept: {kept}; dropped: {dropped}")


@dataclasses.dataclass
class CrashState:
    """One crash state: the cut, the choices made, and the files (name -> bytes) of the bag directory."""

    cut: int  # the cut lies just before this line
    t_cut: float  # the latest moment the power can have failed with this state: that line's time
    model: str
    bag_exists: bool
    files: dict[str, bytes]
    dirs: list[DirState]
    file_states: list[FileState]

    def describe(self) -> str:
        lines = [f"cut before line {self.cut} (t={self.t_cut:.6f}), model {self.model}"]
        lines += [f"  {state.describe()}" for state in self.dirs]
        if not self.bag_exists:
            lines.append("  the bag directory is not there")
        lines += [f"  {state.describe()}" for state in self.file_states]
        return "\n".join(lines)

    def materialize(self, directory: Path) -> Path | None:
        """Write the bag's files into ``directory`` (which must exist); return the bag's path there, or None
        when the crash state has no bag directory."""
        if not self.bag_exists:
            return None
        directory.mkdir(parents=True, exist_ok=True)
        for name, content in self.files.items():
            (directory / name).write_bytes(content)
        return directory


class BagModel:
    """The operations of one bag directory (``bag`` under the trace's root), ready to draw crash states."""

    def __init__(self, trace: Trace, bag: str, model: str = "strict") -> None:
        if model not in MODELS:
            raise ValueError(f"unknown model {model!r}: {MODELS}")
        self.trace = trace
        self.bag = bag
        self.model = model
        self.ops = trace.for_bag(bag)
        if not self.ops:
            raise ValueError(f"no operations on {bag} in the trace")
        creates = [op for op in self.ops if op.kind == "create" and op.dir == ROOT and op.name == bag]
        if len(creates) != 1:
            raise ValueError(f"{bag}: expected one mkdir in the root, found {len(creates)}")
        self.bag_ino = creates[0].ino
        self.entry_ops = [op for op in self.ops if op.kind in ("create", "unlink", "rename")]
        self.data_ops: dict[int, list[Op]] = {}
        for op in self.ops:
            if op.kind in ("write", "trunc"):
                self.data_ops.setdefault(op.ino, []).append(op)
        self.fsyncs = [op for op in self.ops if op.kind in ("fsync", "syncall")]
        self.first_line = self.ops[0].seq_in
        self.last_line = max(op.seq_out for op in self.ops)
        # Cut candidates: just before every entry line and just after every exit line of the bag's operations.
        positions = {self.last_line + 1}
        for op in self.ops:
            positions.add(op.seq_in)
            positions.add(op.seq_out + 1)
        self.positions = sorted(positions)
        self.notable = sorted({p for op in self.ops if op.kind != "write"
                               for p in (op.seq_in, op.seq_out, op.seq_out + 1)})

    # --- the cut ---------------------------------------------------------------------------------

    def t_cut(self, cut: int) -> float:
        times = self.trace.line_times
        return times[cut] if cut < len(times) else times[-1]

    def draw_cut(self, rng: random.Random) -> int:
        """A cut: half of the time at an operation boundary, a quarter at a uniformly random moment of the
        recording, a quarter next to a non-write operation (fsync, create, rename, unlink, truncate)."""
        roll = rng.random()
        if roll < 0.5:
            return rng.choice(self.positions)
        if roll < 0.75:
            t = rng.uniform(self.trace.line_times[self.first_line], self.trace.line_times[self.last_line])
            line = bisect.bisect_left(self.trace.line_times, t)
            return min(max(line, self.first_line), self.last_line + 1)
        return rng.choice(self.notable)

    # --- durability at a cut ---------------------------------------------------------------------

    def _frontiers(self, cut: int) -> tuple[dict[int, int], int]:
        """Per inode, the entry line of the latest fsync of it that returned before the cut; and the same over
        every fsync (for the ext4 model). ``syncall`` counts for every inode."""
        per_inode: dict[int, int] = {}
        latest = -1
        everything = -1
        for op in self.fsyncs:
            if op.seq_out >= cut:
                continue
            latest = max(latest, op.seq_in)
            if op.kind == "syncall":
                everything = max(everything, op.seq_in)
            else:
                per_inode[op.ino] = max(per_inode.get(op.ino, -1), op.seq_in)
        if everything >= 0:
            for ino in set(per_inode) | set(self.data_ops) | {self.bag_ino, ROOT}:
                per_inode[ino] = max(per_inode.get(ino, -1), everything)
        return per_inode, latest

    def durable_data_frontier(self, ino: int, cut: int) -> int:
        return self._frontiers(cut)[0].get(ino, -1)

    # --- drawing a state -------------------------------------------------------------------------

    def sigkill_state(self, cut: int) -> CrashState:
        """What a SIGKILL at the cut leaves: every done operation, nothing in flight (the page cache)."""
        return self._state(cut, None)

    def draw(self, rng: random.Random, cut: int | None = None) -> CrashState:
        if cut is None:
            cut = self.draw_cut(rng)
        return self._state(cut, rng)

    def _state(self, cut: int, rng: random.Random | None) -> CrashState:
        frontiers, latest = self._frontiers(cut)
        # Directory entries: a prefix of each directory's non-durable entry operations.
        done = [op for op in self.entry_ops if op.seq_in < cut and (rng is not None or op.seq_out < cut)]
        done.sort(key=lambda op: (op.seq_out >= cut, op.seq_out if op.seq_out < cut else op.seq_in))
        by_dir: dict[int, list[Op]] = {}
        for op in done:
            by_dir.setdefault(op.dir, []).append(op)
        kept: list[Op] = []
        dir_states = []
        for directory, ops in sorted(by_dir.items()):
            frontier = latest if self.model == "ext4" else frontiers.get(directory, -1)
            if directory in frontiers and frontiers[directory] > frontier:
                frontier = frontiers[directory]  # syncall
            durable = [op for op in ops if op.seq_out < frontier]  # a prefix: ops are in exit order
            pending = ops[len(durable):]
            mode, k = "all", len(pending)
            if rng is not None and pending:
                mode = rng.choice(MODES)
                k = {"all": len(pending), "none": 0}.get(mode, None)
                if k is None:
                    k = rng.randint(0, len(pending))
            kept.extend(durable)
            kept.extend(pending[:k])
            dir_states.append(DirState(self.trace.inode_paths.get(directory, "?"), len(durable), pending, k, mode))
        kept.sort(key=lambda op: op.seq_out)
        # The namespace these entry operations leave.
        names: dict[tuple[int, str], int] = {}
        for op in kept:
            if op.kind == "create":
                names[(op.dir, op.name)] = op.ino
            elif op.kind == "unlink":
                names.pop((op.dir, op.name), None)
            elif op.kind == "rename":
                ino = names.pop((op.dir, op.name), None)
                if ino is not None:
                    names[(op.dir2, op.name2)] = ino
        bag_exists = names.get((ROOT, self.bag)) == self.bag_ino
        files: dict[str, bytes] = {}
        file_states: list[FileState] = []
        if bag_exists:
            for (directory, name), ino in sorted(names.items(), key=lambda item: item[0][1]):
                if directory != self.bag_ino:
                    continue
                if ino in self.trace.directories:
                    raise ValueError(f"{self.bag}/{name}: subdirectories are not modelled")
                content, state = self._file(ino, name, cut, frontiers.get(ino, -1), rng)
                files[name] = content
                file_states.append(state)
        return CrashState(cut, self.t_cut(cut), self.model, bag_exists, files, dir_states, file_states)

    def _file(self, ino: int, name: str, cut: int, frontier: int, rng: random.Random | None
              ) -> tuple[bytes, FileState]:
        ops = [op for op in self.data_ops.get(ino, []) if op.seq_in < cut and (rng is not None or op.seq_out < cut)]
        ops.sort(key=lambda op: (op.seq_out >= cut, op.seq_out if op.seq_out < cut else op.seq_in))
        durable = [op for op in ops if op.seq_out < frontier]
        pending = [op for op in ops if op.seq_out >= frontier]
        image = bytearray()
        size = 0
        for op in durable:
            size = _apply(image, size, op)
        durable_size = size
        # Size after each prefix of the pending operations, and which blocks each write appended over.
        sizes = [size]
        growths: dict[int, list[int]] = {}  # block -> indexes (1-based) of the pending writes whose size growth covers it
        for index, op in enumerate(pending, 1):
            before = sizes[-1]
            after = max(before, op.end) if op.kind == "write" else op.size
            if op.kind == "write" and after > before:
                for block in range(before // BLOCK, (after - 1) // BLOCK + 1):
                    growths.setdefault(block, []).append(index)
            sizes.append(after)
        touched: dict[int, list[int]] = {}  # block -> indexes (1-based) of pending ops that touch it
        for index, op in enumerate(pending, 1):
            for block in _blocks(op, sizes[index - 1]):
                touched.setdefault(block, []).append(index)
        n = len(pending)
        mode = "all"
        if rng is None or not pending:
            k = n
            versions = {block: n for block in touched}
        else:
            mode = rng.choice(MODES)
            if mode == "all":
                k = n
                versions = {block: n for block in touched}
            elif mode == "none":
                k = 0
                versions = {block: 0 for block in touched}
            elif mode == "prefix":
                j = rng.randint(0, n - 1)  # ops 1..j whole, op j+1 torn at a block
                torn = sorted(_blocks(pending[j], sizes[j]))
                cut_at = rng.randint(0, len(torn))
                first = set(torn[:cut_at])
                k = j + (1 if cut_at == len(torn) else 0)
                versions = {}
                for block, indexes in touched.items():
                    versions[block] = j + 1 if block in first else j
            else:
                k = rng.randint(0, n)
                versions = {}
                for block, indexes in touched.items():
                    choices = [0, *indexes, n]
                    roll = rng.random()
                    versions[block] = n if roll < 0.3 else 0 if roll < 0.5 else rng.choice(choices)
            # data=ordered: a block the persisted size exposes through an append holds at least that append.
            # (A block that the size grows over but no write touches is a hole: zeros in every version.)
            for block, indexes in growths.items():
                floor = max((index for index in indexes if index <= k), default=0)
                if floor and block in touched and versions.get(block, 0) < floor:
                    versions[block] = max(i for i in touched[block] if i >= floor) if \
                        rng.random() < 0.5 else floor
        final_size = sizes[k]
        # Apply each pending op to the blocks whose chosen version includes it.
        current = durable_size
        for index, op in enumerate(pending, 1):
            blocks = [block for block in _blocks(op, current) if versions.get(block, 0) >= index]
            current = _apply_blocks(image, current, op, blocks)
        content = bytes(image[:final_size]).ljust(final_size, b"\0")
        state = FileState(name, ino, len(durable), pending, mode, k, final_size,
                          {block: v for block, v in versions.items()}, len(touched))
        return content, state


def _blocks(op: Op, size_before: int) -> range:
    """The 4 KiB blocks an operation changes: a write's bytes; a truncate's cut (shrinking) or nothing."""
    if op.kind == "write":
        if not op.data:
            return range(0)
        return range(op.offset // BLOCK, (op.end - 1) // BLOCK + 1)
    if op.size < size_before:  # the block the cut falls in, and every block after it up to the old end
        return range(op.size // BLOCK, (size_before - 1) // BLOCK + 1)
    return range(0)


def _apply(image: bytearray, size: int, op: Op) -> int:
    """Apply one data operation to a file image; return the new size."""
    if op.kind == "write":
        if len(image) < op.end:
            image.extend(bytes(op.end - len(image)))
        image[op.offset:op.end] = op.data
        return max(size, op.end)
    if op.size < len(image):
        image[op.size:] = bytes(len(image) - op.size)  # truncated bytes read as zeros if the file grows again
    return op.size


def _apply_blocks(image: bytearray, size: int, op: Op, blocks: list[int]) -> int:
    """Apply one data operation to the given blocks of the image only; return the file's size after it (the
    size of the page-cache file, not what persists)."""
    new_size = max(size, op.end) if op.kind == "write" else op.size
    if not blocks:
        return new_size
    if op.kind == "write":
        if len(image) < op.end:
            image.extend(bytes(op.end - len(image)))
        for block in blocks:
            start = max(op.offset, block * BLOCK)
            end = min(op.end, (block + 1) * BLOCK)
            image[start:end] = op.data[start - op.offset:end - op.offset]
    else:
        for block in blocks:
            start = max(op.size, block * BLOCK)
            end = min(len(image), (block + 1) * BLOCK)
            if start < end:
                image[start:end] = bytes(end - start)
    return new_size
