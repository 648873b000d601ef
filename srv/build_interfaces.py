"""Build the interface packages in srv/ into real ROS 2 typesupport, with the PyPI Jazzy wheels only.

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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

SRV_ROOT = pathlib.Path(__file__).resolve().parent
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
    raise RuntimeError("cannot find the ROS 2 Jazzy wheels' share/ folder; install ros-jazzy-rclpy first")


def _load_extensions(loader_name: str, specs: list[str]) -> list:
    """Load rosidl_cli extensions, tolerating the wheels' duplicate entry points (egg-info and dist-info)."""
    from rosidl_cli.command.generate import extensions

    return getattr(extensions, loader_name)(specs=specs, strict=False)


def _generate(package: str, work: pathlib.Path, prefix: pathlib.Path) -> pathlib.Path:
    """Translate, hash and generate code for one package; returns the generation output folder."""
    from rosidl_cli.command.hash.api import generate_type_hashes
    from rosidl_cli.command.translate.api import translate

    os.environ.setdefault("AMENT_PREFIX_PATH", str(prefix))  # the generators locate their templates this way
    source = SRV_ROOT / package
    files = sorted(str(p.relative_to(source)) for p in source.glob("*/*") if p.suffix in (".srv", ".msg"))
    idl_dir = work / "idl" / package
    idl_files = translate(package_name=package, interface_files=[f"{source}:{f}" for f in files],
                          output_format="idl", include_paths=[str(prefix / "share")], output_path=idl_dir)
    idl_tuples = [str(t) for t in idl_files]  # already "<prefix>:<relative path>" tuples
    include_paths = [str(prefix / "share")]
    hash_files = generate_type_hashes(package_name=package, interface_files=idl_tuples,
                                      include_paths=include_paths, output_path=work / "hashes" / package)
    out = work / "gen"
    jobs = [(ext, out / ext.name) for ext in _load_extensions("load_type_extensions", ["c", "py"])]
    jobs += [(ext, out / f"typesupport_{ext.name}")
             for ext in _load_extensions("load_typesupport_extensions", list(TYPESUPPORTS))]
    for ext, ext_out in jobs:
        extra = {"type_description_files": [str(h) for h in hash_files]}
        if "type_description_files" not in inspect.signature(ext.generate).parameters:
            extra = {}  # the py generator takes its hashes from the c generator's output
        ext.generate(package, idl_tuples, include_paths, output_path=ext_out / package, **extra)
    return out


def _compile(sources: list[pathlib.Path], output: pathlib.Path, includes: list[pathlib.Path],
             lib_dirs: list[pathlib.Path], libs: list[str]) -> pathlib.Path:
    """Compile and link one shared library (C or C++ by file suffix), with $ORIGIN as run path.

    Without optimisation: these are the typesupports of a few services and rarely published events, whose speed
    does not matter, and -O0 builds them in about two thirds of the time of -O2 (every install and every wheel the
    tests build pays it)."""
    cxx = any(s.suffix == ".cpp" for s in sources)
    compiler = os.environ.get("CXX", "g++") if cxx else os.environ.get("CC", "gcc")
    cmd = [compiler, "-shared", "-fPIC", "-O0", "-w", *(["-std=c++17"] if cxx else []), "-o", str(output),
           *map(str, sources), *(f"-I{i}" for i in includes), *(f"-L{d}" for d in lib_dirs),
           *(f"-l{lib}" for lib in libs), "-Wl,-rpath,$ORIGIN", "-Wl,--no-as-needed", f"-Wl,-soname,{output.name}"]
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"compiling {output.name} failed:\n{' '.join(cmd)}\n{result.stderr}")
    return output


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


def build_package(package: str, build_dir: pathlib.Path) -> BuiltPackage:
    """Generate and compile one interface package into ``build_dir``."""
    prefix = _ros_prefix()
    work = build_dir / "work" / package
    shutil.rmtree(work, ignore_errors=True)
    gen = _generate(package, work, prefix)
    deps = _dependencies(gen, package)
    out_lib = build_dir / "lib"
    out_lib.mkdir(parents=True, exist_ok=True)
    include = prefix / "include"
    ros_includes = [include, *(p for p in include.iterdir() if p.is_dir())]
    includes = [gen / "c", *(gen / f"typesupport_{ts}" for ts in TYPESUPPORTS), *ros_includes]
    lib_dirs = [out_lib, prefix / "lib"]
    runtime = ["rosidl_runtime_c", "rcutils"]

    def lib(kind: str, sources: list[pathlib.Path], libs: list[str]) -> pathlib.Path:
        return _compile(sources, out_lib / f"lib{package}__{kind}.so", includes, lib_dirs, libs)

    gen_c = lib("rosidl_generator_c", sorted((gen / "c").rglob("*.c")),
                [*(f"{d}__rosidl_generator_c" for d in deps), *runtime])
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
        jobs = {
            "rosidl_typesupport_introspection_c": pool.submit(
                lib, "rosidl_typesupport_introspection_c", sorted((gen / "typesupport_introspection_c").rglob("*.c")),
                [f"{package}__rosidl_generator_c", *(f"{d}__rosidl_typesupport_introspection_c" for d in deps),
                 *(f"{d}__rosidl_generator_c" for d in deps), *runtime]),
            "rosidl_typesupport_fastrtps_c": pool.submit(
                lib, "rosidl_typesupport_fastrtps_c", sorted((gen / "typesupport_fastrtps_c").rglob("*.cpp")),
                [f"{package}__rosidl_generator_c", *(f"{d}__rosidl_typesupport_fastrtps_c" for d in deps),
                 *(f"{d}__rosidl_generator_c" for d in deps), "rosidl_typesupport_fastrtps_c",
                 "rosidl_typesupport_fastrtps_cpp", "fastcdr", *runtime]),
            "rosidl_typesupport_c": pool.submit(
                lib, "rosidl_typesupport_c", sorted((gen / "typesupport_c").rglob("*.cpp")),
                [f"{package}__rosidl_generator_c", "rosidl_typesupport_c", "rcpputils", *runtime]),
        }
        typesupport_libs = {kind: job.result() for kind, job in jobs.items()}

    py_src = gen / "py" / package
    numpy_include = pathlib.Path(__import__("numpy").get_include())
    py_includes = [pathlib.Path(sysconfig.get_paths()["include"]), numpy_include]
    gen_py = _compile(sorted(py_src.rglob("*_s.c")), out_lib / f"lib{package}__rosidl_generator_py.so",
                      [*includes, *py_includes], lib_dirs,
                      [f"{package}__rosidl_generator_c", f"{package}__rosidl_typesupport_c",
                       *(f"{d}__rosidl_generator_py" for d in deps), *(f"{d}__rosidl_generator_c" for d in deps),
                       *runtime])
    ext_suffix = sysconfig.get_config_var("EXT_SUFFIX")
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
        exts = [pool.submit(
            _compile, [py_src / f"_{package}_s.ep.rosidl_typesupport_{ts}.c"],
            py_src / f"{package}_s__rosidl_typesupport_{ts}{ext_suffix}", [*includes, *py_includes], lib_dirs,
            [f"{package}__rosidl_generator_py", f"{package}__rosidl_typesupport_{ts}",
             f"{package}__rosidl_generator_c", "rosidl_runtime_c", "rcutils"]) for ts in TYPESUPPORTS]
        for ext in exts:
            ext.result()
    for c_file in py_src.rglob("*.c"):
        c_file.unlink()
    libraries = [gen_c, *typesupport_libs.values(), gen_py]
    (py_src / "__init__.py").write_text(PACKAGE_INIT.format(
        package=package, libraries=",\n".join(f"    {lib.name!r}" for lib in libraries)))
    python_package = build_dir / "python" / package
    shutil.rmtree(python_package, ignore_errors=True)
    shutil.copytree(py_src, python_package)
    for library in libraries:
        shutil.copy2(library, python_package / library.name)
    _install_share(package, work, build_dir)
    return BuiltPackage(package, python_package, libraries)


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
    the Python (its version and extension suffix), the compilers named by $CC/$CXX, and the versions of the
    ROS wheels and numpy the code is generated from and compiled against."""
    digest = hashlib.sha256()
    for path in sorted(p for p in SRV_ROOT.rglob("*") if p.is_file() and "__pycache__" not in p.parts):
        digest.update(f"{path.relative_to(SRV_ROOT).as_posix()}\0".encode())
        digest.update(path.read_bytes())
    distributions = sorted({f"{d.metadata['Name']}=={d.version}" for d in importlib.metadata.distributions()
                            if d.metadata["Name"].lower().replace("_", "-").startswith(("ros-", "numpy"))})
    for item in (sys.version, sysconfig.get_config_var("EXT_SUFFIX"), os.environ.get("CC", "gcc"),
                 os.environ.get("CXX", "g++"), str(_ros_prefix()), *distributions):
        digest.update(f"{item}\0".encode())
    return digest.hexdigest()


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
    given the tree's finished ``build/interfaces``, then compiles once."""
    digest = inputs_digest()
    built = _already_built(build_dir, digest)
    if built is not None:
        return built
    (build_dir / STAMP).unlink(missing_ok=True)  # a build that stops halfway must not look complete
    built = [build_package(p, build_dir) for p in interface_packages()]
    (build_dir / STAMP).write_text(digest + "\n")
    return built


if __name__ == "__main__":
    for built in build_all(pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "build/interfaces").resolve()):
        print(built.name, built.python_package, *(p.name for p in built.libraries))
