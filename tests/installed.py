"""What a user installs: the project's wheel, built from a clean copy of the tree, in an environment of its own.

The environment is a venv without the project's editable install: its own site-packages holds the wheel
(installed with ``--no-deps``, non-editable), and a ``.pth`` file after it adds the test venv's site-packages for
the dependencies (the ROS 2 wheels, mcap, numpy...), so no dependency is downloaded again. The test venv's
editable finder is never activated there (``.pth`` files in a directory added by a path line are not run), and
``importlib.metadata`` takes the first distribution of a name on ``sys.path``: the wheel's. So a module or an
entry point missing from the wheel is missing in that environment, as it is for a user.
"""
from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
import sysconfig
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: What never belongs in a clean copy even when git is not there to say so.
_NOT_SOURCE = {".git", ".venv", "build", "dist", "__pycache__", ".pytest_cache"}


def clean_copy(source: Path, destination: Path) -> Path:
    """The tracked and untracked-but-not-ignored files of ``source`` (what a fresh clone plus local edits
    holds), copied to ``destination``."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=source,
                            capture_output=True)
    if listed.returncode == 0:
        names = [name for name in listed.stdout.decode().split("\0") if name]
    else:
        names = [str(path.relative_to(source)) for path in source.rglob("*")
                 if path.is_file() and not _NOT_SOURCE & set(path.relative_to(source).parts)]
    for name in names:
        if (source / name).is_file():
            (destination / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source / name, destination / name)
    return destination


def seed_interfaces(source: Path, copy: Path) -> None:
    """Give ``copy`` the interfaces ``source`` has already compiled (``build/interfaces/<distribution>`` of
    the editable installs, one per ROS distribution, without the intermediate files). The wheel build reuses
    them only if they were built from the same inputs (srv/build_interfaces.py compares a digest of the
    definitions, the build script and the toolchain), and compiles them again otherwise: the wheel still holds
    what a clean build makes, without a second compilation per test run."""
    for stamp in (source / "build" / "interfaces").glob("*/inputs.sha256"):
        folder = stamp.parent.relative_to(source)
        shutil.copytree(source / folder, copy / folder, ignore=shutil.ignore_patterns("work"))


def build_wheel(project: Path, wheel_dir: Path) -> Path:
    """Build ``project``'s wheel with the test venv's build tools (no isolated build env: it would download
    the ROS 2 build requirements again) and return its path."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                    "-w", str(wheel_dir), str(project)], check=True, capture_output=True, text=True)
    wheels = sorted(wheel_dir.glob("*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


@dataclass
class InstalledEnv:
    """A venv holding non-editable installs, with the test venv's dependencies behind them."""

    root: Path

    @property
    def python(self) -> Path:
        return self.root / "bin" / "python"

    def script(self, name: str) -> Path:
        return self.root / "bin" / name

    def install(self, *requirements: str | Path) -> None:
        """``pip install --no-deps`` (non-editable) of wheels or project folders into this environment."""
        subprocess.run([str(self.python), "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                        *map(str, requirements)], check=True, capture_output=True, text=True, cwd=self.root)

    def run(self, *args: str | Path, timeout: float = 60.0, **kwargs) -> subprocess.CompletedProcess:
        """Run a command of this environment from its own folder (never the repository: ``''`` on sys.path
        would import the source tree)."""
        return subprocess.run([str(arg) for arg in args], capture_output=True, text=True, timeout=timeout,
                              cwd=self.root, env=self.env(), **kwargs)

    def env(self) -> dict[str, str]:
        env = dict(os.environ, PATH=f"{self.root / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}")
        env.pop("PYTHONPATH", None)
        return env


def make_env(root: Path) -> InstalledEnv:
    """A new venv at ``root`` whose dependencies come from the test venv's site-packages."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root)], check=True)
    env = InstalledEnv(root)
    own = Path(subprocess.run([str(env.python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                              check=True, capture_output=True, text=True).stdout.strip())
    deps = Path(sysconfig.get_paths()["purelib"])
    hooks = [line for pth in sorted(deps.glob("*.pth")) if not pth.name.startswith("__editable__")
             for line in pth.read_text().splitlines() if line.startswith("import ")]
    (own / "zz_test_venv_dependencies.pth").write_text("\n".join([str(deps), *hooks]) + "\n")
    assert site.getsitepackages()  # the test venv is a real venv
    return env
