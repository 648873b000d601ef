"""Build the interface packages in srv/ into real ROS 2 typesupport, with the ROS 2 wheels from PyPI only.

This is what ``rosidl_generate_interfaces()`` does in a colcon build, done from ``setup.py`` so that
``pip install .`` needs nothing but a C compiler: translate .srv/.msg to .idl, compute the RIHS01 type hashes,
generate the C and Python code with the c, fastrtps_c and introspection_c typesupports, and compile:

* ``lib<pkg>__rosidl_generator_c``, ``lib<pkg>__rosidl_typesupport_{c,fastrtps_c,introspection_c}`` and
  ``lib<pkg>__rosidl_generator_py``, placed inside the Python package;
* the Python package ``<pkg>`` with its ``<pkg>_s__rosidl_typesupport_*`` extension modules, and an
  ``__init__.py`` that preloads the libraries.

Why the preload: the middleware finds ``lib<pkg>__rosidl_typesupport_fastrtps_c.so`` by a bare ``dlopen`` of
that name, which only searches the ``LD_LIBRARY_PATH`` the process started with. A library already loaded
under that soname is found first, so preloading works for wheel, editable and ``--target`` installs alike.

Every folder ``srv/<pkg>/`` with ``srv/*.srv`` and ``msg/*.msg`` files is one package.
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import inspect
import logging
import os
import pathlib
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field

from ros_distribution import built_for, distributions, interfaces_build_dir, requirement_name

SRV_ROOT = pathlib.Path(__file__).resolve().parent
PYPROJECT = SRV_ROOT.parent / "pyproject.toml"
TYPESUPPORTS = ("c", "fastrtps_c", "introspection_c")
#: The file in a build folder that names the inputs of the complete build it holds (see :func:`build_all`).
STAMP = "inputs.sha256"
logging.getLogger("rosidl_cli").setLevel(logging.ERROR)  # silence the wheels' duplicate entry point warnings


PACKAGE_INIT = '''"""ROS 2 interfaces {package}, built from srv/{package} of rclpy-ipc-container."""
import ctypes as _ctypes
import pathlib as _pathlib

# The middleware dlopens typesupport libraries by bare name; preloading them makes that name resolve here.
for _library in (
{libraries},
):
    _ctypes.CDLL(str(_pathlib.Path(__file__).with_name(_library)), mode=_ctypes.RTLD_GLOBAL)
'''


@dataclass
class BuiltPackage:
    """Where the build of one interface package put its outputs."""

    name: str
    python_package: pathlib.Path
    libraries: list[pathlib.Path] = field(default_factory=list)


def interface_packages() -> list[str]:
    """Names of the interface packages defined under srv/."""
    return sorted(p.name for p in SRV_ROOT.iterdir()
                  if p.is_dir() and (any(p.glob("srv/*.srv")) or any(p.glob("msg/*.msg"))))


def _ros_prefix() -> pathlib.Path:
    """The prefix holding the ROS wheels' share/, include/ and lib/ (the venv or the isolated build env)."""
    import rosidl_generator_c  # the wheels install share/ and lib/ next to the interpreter prefix

    for prefix in (pathlib.Path(sys.prefix), pathlib.Path(rosidl_generator_c.__file__).parents[4]):
        if (prefix / "share" / "rcl_interfaces").is_dir():
            return prefix
    raise RuntimeError("cannot find the ROS 2 wheels' share/ folder; install the distribution's rclpy first "
                       "(pyproject.toml, tool.ros-distributions)")


def _load_extensions(loader_name: str, specs: list[str]) -> list:
    """Load rosidl_cli extensions, tolerating the wheels' duplicate entry points (egg-info and dist-info)."""
    from rosidl_cli.command.generate import extensions

    return getattr(extensions, loader_name)(specs=specs, strict=False)


def _translate(package: str, work: pathlib.Path, prefix: pathlib.Path) -> tuple[list[str], list[str]]:
    """Translate one package's .srv/.msg files to .idl and compute their type hashes; returns both file lists."""
    from rosidl_cli.command.hash.api import generate_type_hashes
    from rosidl_cli.command.translate.api import translate

    source = SRV_ROOT / package
    files = sorted(str(p.relative_to(source)) for p in source.glob("*/*") if p.suffix in (".srv", ".msg"))
    idl_files = translate(package_name=package, interface_files=[f"{source}:{f}" for f in files],
                          output_format="idl", include_paths=[str(prefix / "share")],
                          output_path=work / "idl" / package)
    idl_tuples = [str(t) for t in idl_files]  # already "<prefix>:<relative path>" tuples
    hash_files = generate_type_hashes(package_name=package, interface_files=idl_tuples,
                                      include_paths=[str(prefix / "share")], output_path=work / "hashes" / package)
    return idl_tuples, [str(h) for h in hash_files]


#: The code generators a package needs: (rosidl_cli loader, extension name, output folder under gen/).
GENERATORS = [("load_type_extensions", "c", "c"), ("load_type_extensions", "py", "py"),
              *(("load_typesupport_extensions", ts, f"typesupport_{ts}") for ts in TYPESUPPORTS)]


def _run_generator(package: str, work: pathlib.Path, prefix: pathlib.Path, loader: str, name: str, folder: str,
                   idl_tuples: list[str], hash_files: list[str]) -> None:
    """Run one code generator on one package (in a worker process: the generators are pure Python)."""
    (ext,) = _load_extensions(loader, [name])
    extra = {"type_description_files": hash_files}
    if "type_description_files" not in inspect.signature(ext.generate).parameters:
        extra = {}  # the py generator takes its hashes from the c generator's output
    ext.generate(package, idl_tuples, [str(prefix / "share")], output_path=work / "gen" / folder / package,
                 **extra)


def _translation_units(library: _Library) -> list[list[pathlib.Path]]:
    """The library's sources grouped into translation units: every ``*__description.c`` alone (each defines the
    same file-level statics, ``implicit_encoding`` and others), all the others together (the generated files name
    everything after their own type), so that the runtime headers they all include are parsed once."""
    alone = [source for source in library.sources if source.name.endswith("__description.c")]
    together = [source for source in library.sources if source not in alone]
    return [*([together] if together else []), *([source] for source in alone)]


def _compile_object(sources: list[pathlib.Path], includes: list[pathlib.Path], output: pathlib.Path) -> pathlib.Path:
    """Compile ``sources`` (C or C++, by suffix) as one translation unit to a position-independent ``output``.

    Without optimisation: these are the typesupports of a few services and rarely published events, whose speed
    does not matter, and -O0 builds them in about two thirds of the time of -O2 (every install and every wheel the
    tests build pays it)."""
    cxx = sources[0].suffix == ".cpp"
    compiler = os.environ.get("CXX", "g++") if cxx else os.environ.get("CC", "gcc")
    source = sources[0]
    if len(sources) > 1:
        source = output.with_suffix(sources[0].suffix)
        source.write_text("".join(f'#include "{s}"\n' for s in sources))
    _run([compiler, "-c", "-fPIC", "-O0", "-w", *(["-std=c++17"] if cxx else []), "-o", str(output), str(source),
          *(f"-I{i}" for i in includes)], output.name)
    return output


def _link(objects: list[pathlib.Path], output: pathlib.Path, lib_dirs: list[pathlib.Path], libs: list[str],
          cxx: bool) -> pathlib.Path:
    """Link one shared library, with $ORIGIN as run path."""
    compiler = os.environ.get("CXX", "g++") if cxx else os.environ.get("CC", "gcc")
    _run([compiler, "-shared", "-o", str(output), *map(str, objects), *(f"-L{d}" for d in lib_dirs),
          *(f"-l{lib}" for lib in libs), "-Wl,-rpath,$ORIGIN", "-Wl,--no-as-needed", f"-Wl,-soname,{output.name}"],
         output.name)
    return output


def _run(cmd: list[str], what: str) -> None:
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"building {what} failed:\n{' '.join(cmd)}\n{result.stderr}")


def _dependencies(gen: pathlib.Path, package: str) -> list[str]:
    """Interface packages the generated C code includes (e.g. rcl_interfaces, builtin_interfaces)."""
    deps: set[str] = set()
    for header in (gen / "c" / package).rglob("*.h"):
        for line in header.read_text().splitlines():
            if line.startswith('#include "') and "/msg/" in line:
                dep = line.split('"')[1].split("/")[0]
                if dep != package:
                    deps.add(dep)
    return sorted(deps)


@dataclass
class _Library:
    """One shared library of a package: its sources, the libraries it links, where it goes."""

    output: pathlib.Path
    sources: list[pathlib.Path]
    includes: list[pathlib.Path]
    libs: list[str]


def _libraries(package: str, build_dir: pathlib.Path, prefix: pathlib.Path) -> list[_Library]:
    """The libraries of one generated package, in link order (each links only those before it)."""
    gen = build_dir / "work" / package / "gen"
    deps = _dependencies(gen, package)
    out_lib = build_dir / "lib"
    include = prefix / "include"
    includes = [gen / "c", *(gen / f"typesupport_{ts}" for ts in TYPESUPPORTS), include,
                *(p for p in include.iterdir() if p.is_dir())]
    py_includes = [*includes, pathlib.Path(sysconfig.get_paths()["include"]),
                   pathlib.Path(__import__("numpy").get_include())]
    runtime = ["rosidl_runtime_c", "rcutils"]
    own_c = f"{package}__rosidl_generator_c"

    def lib(kind: str, suffix: str, libs: list[str]) -> _Library:
        folder = gen / ("c" if kind == "rosidl_generator_c" else kind.replace("rosidl_", ""))
        return _Library(out_lib / f"lib{package}__{kind}.so", sorted(folder.rglob(f"*{suffix}")), includes, libs)

    py_src = gen / "py" / package
    ext_suffix = sysconfig.get_config_var("EXT_SUFFIX")
    return [
        lib("rosidl_generator_c", ".c", [*(f"{d}__rosidl_generator_c" for d in deps), *runtime]),
        lib("rosidl_typesupport_introspection_c", ".c",
            [own_c, *(f"{d}__rosidl_typesupport_introspection_c" for d in deps),
             *(f"{d}__rosidl_generator_c" for d in deps), *runtime]),
        lib("rosidl_typesupport_fastrtps_c", ".cpp",
            [own_c, *(f"{d}__rosidl_typesupport_fastrtps_c" for d in deps), *(f"{d}__rosidl_generator_c" for d in deps),
             "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp", "fastcdr", *runtime]),
        lib("rosidl_typesupport_c", ".cpp", [own_c, "rosidl_typesupport_c", "rcpputils", *runtime]),
        _Library(out_lib / f"lib{package}__rosidl_generator_py.so", sorted(py_src.rglob("*_s.c")), py_includes,
                 [own_c, f"{package}__rosidl_typesupport_c", *(f"{d}__rosidl_generator_py" for d in deps),
                  *(f"{d}__rosidl_generator_c" for d in deps), *runtime]),
        *(_Library(py_src / f"{package}_s__rosidl_typesupport_{ts}{ext_suffix}",
                   [py_src / f"_{package}_s.ep.rosidl_typesupport_{ts}.c"], py_includes,
                   [f"{package}__rosidl_generator_py", f"{package}__rosidl_typesupport_{ts}", own_c, *runtime])
          for ts in TYPESUPPORTS),
    ]


def _finish_package(package: str, build_dir: pathlib.Path, libraries: list[_Library]) -> BuiltPackage:
    """Lay out the Python package of one compiled interface package, and its share/ folder."""
    work = build_dir / "work" / package
    py_src = work / "gen" / "py" / package
    for c_file in py_src.rglob("*.c"):
        c_file.unlink()
    for o_file in py_src.rglob("*.o"):
        o_file.unlink()
    shared = [library.output for library in libraries if library.output.parent == build_dir / "lib"]
    (py_src / "__init__.py").write_text(PACKAGE_INIT.format(
        package=package, libraries=",\n".join(f"    {lib.name!r}" for lib in shared)))
    python_package = build_dir / "python" / package
    shutil.rmtree(python_package, ignore_errors=True)
    shutil.copytree(py_src, python_package)
    for library in shared:
        shutil.copy2(library, python_package / library.name)
    _install_share(package, work, build_dir)
    return BuiltPackage(package, python_package, shared)


def build_packages(packages: list[str], build_dir: pathlib.Path) -> list[BuiltPackage]:
    """Generate and compile ``packages`` into ``build_dir``, on every core.

    The code generators run in worker processes (one per package and generator: they are pure Python), then the
    translation units of every library (:func:`_translation_units`) compile at once, and the libraries link in
    dependency order.
    """
    prefix = _ros_prefix()
    os.environ.setdefault("AMENT_PREFIX_PATH", str(prefix))  # the generators locate their templates this way
    works = {package: build_dir / "work" / package for package in packages}
    for work in works.values():
        shutil.rmtree(work, ignore_errors=True)
    (build_dir / "lib").mkdir(parents=True, exist_ok=True)
    workers = os.cpu_count() or 2
    with ProcessPoolExecutor(max_workers=workers) as pool:
        translated = dict(zip(packages, pool.map(_translate, packages, works.values(), [prefix] * len(packages))))
        for job in [pool.submit(_run_generator, package, works[package], prefix, *generator, *translated[package])
                    for package in packages for generator in GENERATORS]:
            job.result()
    libraries = {package: _libraries(package, build_dir, prefix) for package in packages}
    objects_dir = build_dir / "work" / "objects"
    objects_dir.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        objects = {id(library): [pool.submit(_compile_object, unit, library.includes,
                                             objects_dir / f"{library.output.name}.{n}.o")
                                 for n, unit in enumerate(_translation_units(library))]
                   for package_libraries in libraries.values() for library in package_libraries}
        for package_libraries in libraries.values():
            for library in package_libraries:
                _link([job.result() for job in objects[id(library)]], library.output,
                      [build_dir / "lib", prefix / "lib"], library.libs,
                      cxx=any(s.suffix == ".cpp" for s in library.sources))
    return [_finish_package(package, build_dir, libraries[package]) for package in packages]


def _install_share(package: str, work: pathlib.Path, build_dir: pathlib.Path) -> None:
    """Lay out share/<pkg>/{srv,msg} with .srv/.msg/.idl/.json and the ament index marker, as colcon does.

    Tools that look interface definitions up by package (ament_index_python, a recorder's message
    definitions) then find these packages like any other installed ROS package.
    """
    share = build_dir / "share" / package
    shutil.rmtree(share, ignore_errors=True)
    marker = build_dir / "share" / "ament_index" / "resource_index" / "packages" / package
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.touch()
    for sub in ("srv", "msg"):
        files = [*(SRV_ROOT / package / sub).glob("*.*"), *(work / "idl" / package / sub).glob("*.idl"),
                 *(work / "hashes" / package / sub).glob("*.json")]
        if files:
            (share / sub).mkdir(parents=True, exist_ok=True)
            for f in files:
                shutil.copy2(f, share / sub / f.name)


def inputs_digest() -> str:
    """A digest of everything a build's output depends on: the files under srv/ (definitions and this script),
    the Python (its version and extension suffix), the compilers named by $CC/$CXX, and the versions of the ROS
    wheels and numpy among what the build requirements pull in: the code is generated from them and compiled
    against them. Not the test extras' ROS wheels (test_msgs, installed after the build: the wheel the tests
    build must not compile again), nor the build tools (which packages a build process sees varies)."""
    digest = hashlib.sha256()
    for path in sorted(p for p in SRV_ROOT.rglob("*") if p.is_file() and "__pycache__" not in p.parts):
        digest.update(f"{path.relative_to(SRV_ROOT).as_posix()}\0".encode())
        digest.update(path.read_bytes())
    distributions = sorted(f"{d.metadata['Name']}=={d.version}" for d in _build_distributions()
                           if d.metadata["Name"].lower().replace("_", "-").startswith(("ros-", "numpy")))
    for item in (sys.version, sysconfig.get_config_var("EXT_SUFFIX"), os.environ.get("CC", "gcc"),
                 os.environ.get("CXX", "g++"), str(_ros_prefix()), *distributions):
        digest.update(f"{item}\0".encode())
    return digest.hexdigest()


def _build_distributions() -> list[importlib.metadata.Distribution]:
    """The installed distributions named by the build requirements (pyproject.toml's, and the ROS wheels of the
    distribution built for), and everything they require."""
    requires = [*tomllib.loads(PYPROJECT.read_text())["build-system"]["requires"],
                *distributions()[built_for()]["requires"]]
    found: dict[str, importlib.metadata.Distribution] = {}
    pending = [requirement_name(r) for r in requires]
    while pending:
        wanted = pending.pop()
        if wanted in found:
            continue
        try:
            distribution = importlib.metadata.distribution(wanted)
        except importlib.metadata.PackageNotFoundError:
            continue
        found[wanted] = distribution
        pending += [requirement_name(r) for r in distribution.requires or []]  # every marker: more, never fewer
    return list(found.values())


def _already_built(build_dir: pathlib.Path, digest: str) -> list[BuiltPackage] | None:
    """The packages in ``build_dir`` if a build of exactly these inputs completed there, else None."""
    stamp = build_dir / STAMP
    if not stamp.is_file() or stamp.read_text().strip() != digest:
        return None
    built = []
    for package in interface_packages():
        python_package = build_dir / "python" / package
        if not (python_package / "__init__.py").is_file():
            return None
        built.append(BuiltPackage(package, python_package, sorted(python_package.glob("lib*.so"))))
    return built


def build_all(build_dir: pathlib.Path) -> list[BuiltPackage]:
    """Build every interface package under srv/ into ``build_dir``, unless a completed build of the same inputs
    (:func:`inputs_digest`) is already there: an editable install followed by a wheel build, or a clean copy
    given the tree's finished ``build/interfaces/<distribution>``, then compiles once."""
    digest = inputs_digest()
    built = _already_built(build_dir, digest)
    if built is not None:
        return built
    (build_dir / STAMP).unlink(missing_ok=True)  # a build that stops halfway must not look complete
    built = build_packages(interface_packages(), build_dir)
    (build_dir / STAMP).write_text(digest + "\n")
    return built


if __name__ == "__main__":
    default_dir = SRV_ROOT.parent / interfaces_build_dir(built_for())
    for built in build_all(pathlib.Path(sys.argv[1]).resolve() if len(sys.argv) > 1 else default_dir):
        print(built.name, built.python_package, *(p.name for p in built.libraries))
