# Fresh-machine entry points: `make demo` and `make test` create .venv, install the project (building the
# srv/ interfaces with the system C compiler) and run. Every ROS run is isolated: a random ROS_DOMAIN_ID and
# discovery limited to localhost. The build requirements, the dependencies and the test extras go into .venv in
# one pip run (one resolution), then the project is built there without an isolated build environment: the ROS
# wheels are installed once, and the wheel the tests build from a clean copy reuses the interfaces compiled here
# (srv/build_interfaces.py compares their inputs.sha256).
#
# ROS_DISTRO picks the ROS 2 distribution (pyproject.toml, tool.ros-distributions): Jazzy by default, in .venv;
# `make test ROS_DISTRO=kilted` sets up and tests Kilted's wheels in .venv-kilted. The interfaces of each are
# built into build/interfaces/<distribution>, so both venvs can hold the same tree.
#
# PYTHON is the interpreter the venvs are made from: the distribution's own Python 3.11 where the machine has one
# that can make a venv and compile against its headers (Debian's python3.11-venv and python3.11-dev), python3 on
# PATH otherwise. Debian builds its interpreter with profile-guided optimization and links it statically; a plain
# source build such as pyenv's (shared libpython, no PGO) is slower in every ROS process: a command 14 % and a
# container's imports 12 % more CPU, the suite 7 % longer (CHANGELOG.md). Set PYTHON to choose; a venv made
# from another interpreter stays until `make clean`.
SYSTEM_PYTHON := /usr/bin/python3.11
ifeq ($(origin PYTHON),undefined)
PYTHON := $(if $(shell $(SYSTEM_PYTHON) -c 'import ensurepip, pathlib, sysconfig; \
  assert (pathlib.Path(sysconfig.get_path("include")) / "Python.h").exists()' 2>/dev/null && echo ok),$(SYSTEM_PYTHON),python3)
endif
DEFAULT_DISTRO := $(shell $(PYTHON) srv/ros_distribution.py default)
ROS_DISTRO ?= $(DEFAULT_DISTRO)
export ROS_DISTRO
VENV := $(if $(filter $(DEFAULT_DISTRO),$(ROS_DISTRO)),.venv,.venv-$(ROS_DISTRO))
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST

.PHONY: setup demo test sweep bench clean ffmpeg bytecode test-bytecode

# pip compiles what it installs, but an editable install leaves the tree's modules (and the interfaces built into
# build/) as source: where PYTHONDONTWRITEBYTECODE is set, every container and CLI process the tests start would
# compile them again. compileall writes the bytecode once; it skips what is up to date.
SOURCES := component_container components baglib ipc_component ipc_testing build/interfaces/$(ROS_DISTRO) tests examples

$(STAMP): pyproject.toml setup.py $(wildcard srv/*/*/*) srv/build_interfaces.py srv/ros_distribution.py
	$(PYTHON) srv/ros_distribution.py requirements >/dev/null  # a ROS_DISTRO without pins stops here
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python srv/ros_distribution.py requirements | $(BIN)/python -m pip install -q -r /dev/stdin
	$(BIN)/python -m pip install -q --no-build-isolation --no-deps -e .
	touch $(STAMP)

setup: $(STAMP)

bytecode: $(STAMP)
	$(BIN)/python -m compileall -q -j 0 $(SOURCES) >/dev/null

# pytest rewrites the asserts of every test module it imports, in each xdist worker (5.6 CPU-s for the suite's
# modules), and caches the result in __pycache__ only where bytecode may be written. With PYTHONDONTWRITEBYTECODE
# set, every worker of every run rewrote them all: 11 s of the suite's start on 2 cores. Collecting once, here,
# with bytecode allowed, a process per core, writes that cache; the workers then read it. A module that fails to
# collect is reported by the run itself.
TEST_MODULES := $(wildcard tests/test_*.py)

test-bytecode: $(STAMP)
	@printf '%s\n' $(TEST_MODULES) | xargs -P $$(nproc) -n $$(( ($(words $(TEST_MODULES)) + $$(nproc) - 1) / $$(nproc) )) \
	  env -u PYTHONDONTWRITEBYTECODE $(BIN)/python -m pytest -q --collect-only -p no:cacheprovider >/dev/null || true

demo: $(STAMP) bytecode
	ROS_DOMAIN_ID=$$(shuf -i 1-100 -n 1) $(BIN)/python examples/record_demo.py

# Workers of pytest-xdist: more than the 2 cores, since most tests wait on ROS discovery and other processes. On the
# 2-core machine, the same code: 4 workers 273-275 s at 86 % busy, 5 workers 243-252 s at 93-94 %, 6 workers 271 s
# at 97 % (with 60 CPU-s more: every worker's processes compete).
TEST_WORKERS ?= 5

# The image encoder's tests decode its output with Debian's ffmpeg program, a decoder the project does not use.
ffmpeg:
	@command -v ffmpeg >/dev/null || { [ "$$(id -u)" = 0 ] && apt-get update -qq && apt-get install -y -qq ffmpeg >/dev/null; } \
	  || { echo "make test needs the ffmpeg program: sudo apt-get install ffmpeg" >&2; exit 1; }

# One OpenBLAS thread in the processes the tests start: every ROS Python process imports numpy, whose OpenBLAS
# starts a thread per core that spins for a while; the suite starts hundreds of processes and does no linear algebra.
test: $(STAMP) ffmpeg bytecode test-bytecode
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --durations=25 tests

# The sweep also checks that Ray Data reads uploaded bags (tests/test_cluster_read.py): the `cluster` extra, which
# `make test` does not install.
CLUSTER_STAMP := $(VENV)/.cluster-installed

$(CLUSTER_STAMP): $(STAMP)
	$(BIN)/python srv/ros_distribution.py extra cluster | $(BIN)/python -m pip install -q -r /dev/stdin
	touch $(CLUSTER_STAMP)

sweep: $(STAMP) $(CLUSTER_STAMP) ffmpeg bytecode test-bytecode
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --durations=25 -m sweep tests

bench: $(STAMP)
	ROS_DOMAIN_ID=$$(shuf -i 1-100 -n 1) $(BIN)/python benchmarks/record_bench.py $(BENCH_ARGS)

clean:
	rm -rf .venv .venv-* build *.egg-info
