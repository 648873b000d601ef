"""Parse an ``strace -f -xx`` log into the file-system operations of the bags under one directory.

The log is what ``capture.py`` records: every line is ``PID UNIXTIME.NS syscall(args) = ret`` (or its
``<unfinished ...>`` / ``<... resumed>`` halves when threads interleave), strings printed all in hex (``-xx``)
and at full length (``-s``), so the written bytes are in the log. The parser keeps its own picture of the
page cache's namespace under the watched root (path -> inode) and of every file descriptor (inode, file
position, shared between dup'ed descriptors and CLONE_FILES threads), and emits, for the watched subtree only:

* entry operations of a directory: ``create`` (a new file or directory), ``unlink``, ``rename``;
* data operations of a file: ``write`` (offset and bytes, whatever the syscall: write, pwrite64, writev,
  pwritev, pwritev2) and ``trunc`` (ftruncate, truncate, O_TRUNC);
* ``fsync`` of a file or a directory (fsync, fdatasync), and ``syncall`` (sync, syncfs).

Each operation has its entry and exit line (``seq_in``, ``seq_out``) and times: an operation is *done* at a cut
after its exit line, *in flight* between the two. Line times (``line_times``) give the moment of a cut.
"""
from __future__ import annotations

import dataclasses
import os
import re
from array import array
from pathlib import Path

__all__ = ["Op", "Trace", "TraceError", "parse_trace", "ROOT"]

ROOT = 0  # inode number of the watched root directory (exists and is durable before the capture)


class TraceError(ValueError):
    """The log cannot be read as a trace of the watched files (truncated data, an unknown descriptor...)."""


@dataclasses.dataclass
class Op:
    """One file-system operation on the watched subtree."""

    seq_in: int  # line of the syscall's entry
    seq_out: int  # line of its exit (== seq_in when strace printed it whole)
    t_in: float
    t_out: float
    kind: str  # create | unlink | rename | write | trunc | fsync | syncall
    ino: int = -1  # the file written, truncated, fsynced, created, unlinked or renamed
    dir: int = -1  # entry operations: the directory (rename: the source directory)
    name: str = ""  # entry operations: the name (rename: the source name)
    dir2: int = -1  # rename: the target directory
    name2: str = ""  # rename: the target name
    replaced: int = -1  # rename: the inode the target name held before, if any
    offset: int = 0  # write: file offset
    data: bytes = b""  # write: the bytes written (as many as the syscall returned)
    size: int = 0  # trunc: the new size
    is_dir: bool = False  # create: a directory (mkdir)
    syscall: str = ""  # what the process called (for reports)
    path: str = ""  # the path, relative to the watched root, at the time of the call (for reports)

    @property
    def end(self) -> int:
        return self.offset + len(self.data)

    def describe(self) -> str:
        where = f"line {self.seq_out}" + (f" (from {self.seq_in})" if self.seq_in != self.seq_out else "")
        if self.kind == "write":
            what = f"{self.syscall} {self.path} [{self.offset}, {self.end})"
        elif self.kind == "trunc":
            what = f"{self.syscall} {self.path} to {self.size}"
        elif self.kind == "rename":
            what = f"rename {self.path} -> {self.name2}"
        else:
            what = f"{self.syscall or self.kind} {self.path}"
        return f"{what} @{where}"


@dataclasses.dataclass
class Trace:
    """The operations on the watched subtree, in the order of their exit lines, and every line's time."""

    root: str
    ops: list[Op]
    line_times: array  # seconds since the epoch of every line of the log, by line number
    inode_paths: dict[int, str]  # inode -> its first path relative to the root (for reports)
    directories: set[int]
    lines: int = 0

    def bag_of(self, op: Op) -> str:
        """The top-level entry under the root an operation belongs to (a bag directory's name)."""
        path = op.path
        return path.split("/", 1)[0]

    def for_bag(self, bag: str) -> list[Op]:
        """The operations on one bag directory: its creation in the root and everything inside it."""
        return [op for op in self.ops if self.bag_of(op) in (bag, "")]  # "": the root itself (its fsyncs)


@dataclasses.dataclass
class _Open:
    """An open file description: shared by dup'ed descriptors and by threads."""

    ino: int | None  # None: outside the watched subtree
    path: str  # absolute path at open time
    pos: int = 0
    append: bool = False


_LINE = re.compile(r"^(\d+)\s+(\d+)\.(\d+) (.*)$")
_CALL = re.compile(r"^([a-z_0-9]+)\((.*)$", re.S)
_RESUMED = re.compile(r"^<\.\.\. ([a-z_0-9]+) resumed>(.*)$", re.S)
_UNFINISHED = " <unfinished ...>"
_RET = re.compile(r"\) += (-?\d+|\?|0x[0-9a-f]+)(?: .*)?$", re.S)
_STRING = re.compile(r'"((?:\\x[0-9a-f]{2})*)"(\.\.\.)?')

_WRITES = {"write", "pwrite64", "writev", "pwritev", "pwritev2"}
_WATCHED_CALLS = _WRITES | {
    "open", "openat", "openat2", "creat", "close", "lseek", "ftruncate", "truncate", "fsync", "fdatasync",
    "rename", "renameat", "renameat2", "unlink", "unlinkat", "mkdir", "mkdirat", "rmdir", "dup", "dup2", "dup3",
    "fcntl", "fallocate", "link", "linkat", "sync", "syncfs", "clone", "clone3", "fork", "vfork",
}


#: What _split_args looks at: a whole string (all-hex: no quote inside), a bracket or a comma.
_ARG_TOKENS = re.compile(r'"[^"]*"|[\[\]{}(),]')


def _split_args(text: str) -> list[str]:
    """Split a syscall's argument text at its top-level commas. The strings (a write's data: megabytes of
    ``\\xNN``) are skipped whole by the regular expression, not walked character by character."""
    parts: list[str] = []
    depth = 0
    start = 0
    for match in _ARG_TOKENS.finditer(text):
        token = match.group()
        if token in ("[", "{", "("):
            depth += 1
        elif token in ("]", "}", ")"):
            depth -= 1
        elif token == "," and depth == 0:
            parts.append(text[start:match.start()].strip())
            start = match.end()
    tail = text[start:].strip()
    if tail:
        parts.append(tail)
    return parts


def _string(text: str, what: str) -> bytes:
    match = _STRING.search(text)
    if match is None:
        raise TraceError(f"no string in {what}: {text[:80]!r}")
    if match.group(2):
        raise TraceError(f"{what}: strace cut a string (raise -s)")
    return bytes.fromhex(match.group(1).replace("\\x", ""))


def _int(text: str) -> int:
    return int(text, 0)


class _Parser:
    def __init__(self, root: Path, cwd: Path) -> None:
        self.root = os.path.normpath(str(root))
        self.cwd = os.path.normpath(str(cwd))
        self.namespace: dict[str, int] = {self.root: ROOT}  # absolute path -> inode (page cache view)
        self.directories: set[int] = {ROOT}
        self.inode_paths: dict[int, str] = {ROOT: ""}
        self.next_ino = 1
        self.tables: dict[int, dict[int, _Open]] = {}  # tid -> fd table (shared objects between threads)
        self.ops: list[Op] = []
        self.pending: dict[int, tuple[int, float, str]] = {}  # tid -> (seq_in, t_in, entry text)
        self.line_times = array("d")

    # --- paths -----------------------------------------------------------------------------------

    def watched(self, path: str) -> bool:
        return path == self.root or path.startswith(self.root + "/")

    def relative(self, path: str) -> str:
        return "" if path == self.root else path[len(self.root) + 1:]

    def resolve(self, tid: int, dirfd: str, raw: str) -> str:
        path = os.fsdecode(_string(raw, "path"))
        if not path.startswith("/"):
            base = self.cwd
            if dirfd not in ("AT_FDCWD", ""):
                entry = self.table(tid).get(_int(dirfd))
                if entry is None:
                    raise TraceError(f"path {path!r} relative to an unknown descriptor {dirfd}")
                base = entry.path
            path = os.path.join(base, path)
        return os.path.normpath(path)

    def table(self, tid: int) -> dict[int, _Open]:
        if tid not in self.tables:
            # The first process seen, or a thread whose creation was not traced: one table for the process.
            self.tables[tid] = next(iter(self.tables.values())) if self.tables else {}
        return self.tables[tid]

    def new_inode(self, path: str, is_dir: bool) -> int:
        ino = self.next_ino
        self.next_ino += 1
        self.inode_paths[ino] = self.relative(path)
        if is_dir:
            self.directories.add(ino)
        return ino

    def parent(self, path: str) -> int:
        parent = os.path.dirname(path)
        if parent not in self.namespace:
            raise TraceError(f"{path}: parent directory unknown to the trace (created outside it?)")
        return self.namespace[parent]

    # --- operations ------------------------------------------------------------------------------

    def emit(self, timing: tuple[int, int, float, float], kind: str, syscall: str, path: str, **fields) -> Op:
        seq_in, seq_out, t_in, t_out = timing
        op = Op(seq_in, seq_out, t_in, t_out, kind, syscall=syscall, path=self.relative(path), **fields)
        self.ops.append(op)
        return op

    def create(self, timing, syscall: str, path: str, is_dir: bool) -> int:
        ino = self.new_inode(path, is_dir)
        self.emit(timing, "create", syscall, path, ino=ino, dir=self.parent(path), name=os.path.basename(path),
                  is_dir=is_dir)
        self.namespace[path] = ino
        return ino

    def remove(self, timing, syscall: str, path: str) -> None:
        ino = self.namespace.pop(path, None)
        if ino is None:
            return  # not ours (or already gone): the call failed or raced; nothing to model
        self.emit(timing, "unlink", syscall, path, ino=ino, dir=self.parent(path), name=os.path.basename(path))

    def rename(self, timing, syscall: str, source: str, target: str) -> None:
        ino = self.namespace.get(source)
        if ino is None:
            if self.watched(target):
                raise TraceError(f"rename into the watched tree from outside it: {source} -> {target}")
            return
        if not self.watched(target):
            raise TraceError(f"rename out of the watched tree: {source} -> {target}")
        replaced = self.namespace.get(target, -1)
        self.emit(timing, "rename", syscall, source, ino=ino, dir=self.parent(source),
                  name=os.path.basename(source), dir2=self.parent(target), name2=os.path.basename(target),
                  replaced=replaced)
        del self.namespace[source]
        self.namespace[target] = ino
        if ino in self.directories:  # move what lies below it too
            prefix = source + "/"
            for path in [p for p in self.namespace if p.startswith(prefix)]:
                self.namespace[target + path[len(source):]] = self.namespace.pop(path)

    # --- syscalls --------------------------------------------------------------------------------

    def syscall(self, tid: int, name: str, args_text: str, ret: int, timing) -> None:
        if ret < 0 or name not in _WATCHED_CALLS:
            return
        table = self.table(tid)
        if name in _WRITES:
            fd = _int(args_text.split(",", 1)[0])
            entry = table.get(fd)
            if entry is None or entry.ino is None:
                return
            args = _split_args(args_text)
            if name in ("write", "pwrite64"):
                data = _string(args[1], name)
            else:
                data = b"".join(_string(part, name) for part in re.findall(r'iov_base=("(?:[^"]*)"(?:\.\.\.)?)',
                                                                             args[1]))
            data = data[:ret]
            if name in ("write", "writev"):
                offset = entry.pos
                entry.pos += ret
            else:
                offset = _int(args[3])
            self.emit(timing, "write", name, entry.path, ino=entry.ino, offset=offset, data=data)
            return
        args = _split_args(args_text)
        if name in ("open", "openat", "creat", "openat2"):
            if name == "open":
                dirfd, raw, flags = "AT_FDCWD", args[0], args[1]
            elif name == "creat":
                dirfd, raw, flags = "AT_FDCWD", args[0], "O_WRONLY|O_CREAT|O_TRUNC"
            elif name == "openat":
                dirfd, raw, flags = args[0], args[1], args[2]
            else:
                dirfd, raw = args[0], args[1]
                flags = re.search(r"flags=([A-Z_|0-9]+)", args[2]).group(1)
            path = self.resolve(tid, dirfd, raw)
            ino: int | None = None
            if self.watched(path):
                ino = self.namespace.get(path)
                if ino is None:
                    if "O_CREAT" not in flags:
                        raise TraceError(f"{path} opened but unknown to the trace")
                    ino = self.create(timing, name, path, is_dir=False)
                elif "O_TRUNC" in flags and ino not in self.directories:
                    self.emit(timing, "trunc", f"{name}(O_TRUNC)", path, ino=ino, size=0)
            table[ret] = _Open(ino, path, append="O_APPEND" in flags)
        elif name == "close":
            table.pop(_int(args[0]), None)
        elif name == "lseek":
            entry = table.get(_int(args[0]))
            if entry is not None:
                entry.pos = ret
        elif name in ("dup", "dup2", "dup3") or (name == "fcntl" and args[1].startswith("F_DUPFD")):
            entry = table.get(_int(args[0]))
            if entry is not None:
                table[ret] = entry
            else:
                table.pop(ret, None)
        elif name == "ftruncate":
            entry = table.get(_int(args[0]))
            if entry is not None and entry.ino is not None:
                self.emit(timing, "trunc", name, entry.path, ino=entry.ino, size=_int(args[1]))
        elif name == "truncate":
            path = self.resolve(tid, "AT_FDCWD", args[0])
            if self.watched(path) and path in self.namespace:
                self.emit(timing, "trunc", name, path, ino=self.namespace[path], size=_int(args[1]))
        elif name in ("fsync", "fdatasync"):
            entry = table.get(_int(args[0]))
            if entry is not None and entry.ino is not None:
                self.emit(timing, "fsync", name, entry.path, ino=entry.ino)
        elif name in ("sync", "syncfs"):
            self.emit(timing, "syncall", name, self.root)
        elif name in ("mkdir", "mkdirat"):
            dirfd, raw = ("AT_FDCWD", args[0]) if name == "mkdir" else (args[0], args[1])
            path = self.resolve(tid, dirfd, raw)
            if self.watched(path):
                self.create(timing, name, path, is_dir=True)
        elif name in ("unlink", "rmdir"):
            path = self.resolve(tid, "AT_FDCWD", args[0])
            if self.watched(path):
                self.remove(timing, name, path)
        elif name == "unlinkat":
            path = self.resolve(tid, args[0], args[1])
            if self.watched(path):
                self.remove(timing, name, path)
        elif name in ("rename", "renameat", "renameat2"):
            if name == "rename":
                source = self.resolve(tid, "AT_FDCWD", args[0])
                target = self.resolve(tid, "AT_FDCWD", args[1])
            else:
                source = self.resolve(tid, args[0], args[1])
                target = self.resolve(tid, args[2], args[3])
            if self.watched(source) or self.watched(target):
                if name == "renameat2" and "RENAME_EXCHANGE" in args[4]:
                    raise TraceError("renameat2(RENAME_EXCHANGE) is not modelled")
                self.rename(timing, name, source, target)
        elif name in ("link", "linkat"):
            target = self.resolve(tid, "AT_FDCWD", args[1]) if name == "link" else \
                self.resolve(tid, args[2], args[3])
            if self.watched(target):
                raise TraceError(f"hard link {target}: not modelled")
        elif name == "fallocate":
            entry = table.get(_int(args[0]))
            if entry is not None and entry.ino is not None:
                raise TraceError(f"fallocate on {entry.path}: not modelled")
        elif name in ("clone", "clone3", "fork", "vfork"):
            shared = "CLONE_FILES" in args_text
            self.tables[ret] = table if shared else dict(table)

    def line(self, seq: int, text: str) -> None:
        match = _LINE.match(text)
        if match is None:
            raise TraceError(f"line {seq}: not a strace -f line: {text[:80]!r}")
        tid = int(match.group(1))
        t = float(f"{match.group(2)}.{match.group(3)}")
        if self.line_times and t < self.line_times[-1]:
            t = self.line_times[-1]  # a line's time is its syscall's entry: keep the times of the lines in order
        self.line_times.append(t)
        rest = match.group(4)
        if rest.startswith("+++") or rest.startswith("---"):
            return
        resumed = _RESUMED.match(rest)
        if resumed is not None:
            name, tail = resumed.groups()
            started = self.pending.pop(tid, None)
            if started is None:
                raise TraceError(f"line {seq}: {name} resumed without its start")
            seq_in, t_in, head = started
            self.finish(tid, name, head + tail, (seq_in, seq, t_in, t))
            return
        call = _CALL.match(rest)
        if call is None:
            raise TraceError(f"line {seq}: cannot read {rest[:80]!r}")
        name, tail = call.groups()
        if tail.endswith(_UNFINISHED):
            self.pending[tid] = (seq, t, tail[:-len(_UNFINISHED)])
            return
        self.finish(tid, name, tail, (seq, seq, t, t))

    def finish(self, tid: int, name: str, text: str, timing) -> None:
        if name not in _WATCHED_CALLS:
            return
        ret_match = _RET.search(text)
        if ret_match is None or ret_match.group(1) == "?":
            return  # the process exited inside the call
        ret = _int(ret_match.group(1))
        self.syscall(tid, name, text[:ret_match.start()], ret, timing)


def parse_trace(log: Path, root: Path, cwd: Path) -> Trace:
    """Read a ``capture.py`` strace log; ``root`` is the watched directory (it existed, durably, before)."""
    parser = _Parser(root, cwd)
    with open(log, encoding="ascii", errors="strict") as lines:
        for seq, text in enumerate(lines):
            parser.line(seq, text.rstrip("\n"))
    return Trace(parser.root, parser.ops, parser.line_times, parser.inode_paths, parser.directories,
                 len(parser.line_times))
