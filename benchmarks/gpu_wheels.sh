#!/usr/bin/env bash
# Wheels for benchmarks/gpu_check.sh on a GPU machine whose python 3.12 has its own torch but not
# this project's other packages: cp312 manylinux wheels of the pins (never torch) and srdcil's own
# wheel, into .whl/ (ignored by git). Run here, from the repo root, with pip and network access.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p .whl
PLAT="--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64"
dl() { python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $PLAT -d .whl "$@"; }
dl torchrl==0.14.1 tensordict==0.14.3 hydra-core==1.3.8 omegaconf==2.3.1 antlr4-python3-runtime==4.9.3 \
   hydra-joblib-launcher==1.2.0 joblib pyvers orjson cloudpickle mujoco==3.11.0 glfw gymnasium==1.4.0 \
   farama-notifications tqdm pyyaml
python3 -m pip wheel -q --no-deps -w .whl .
ls .whl
