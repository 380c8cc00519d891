#!/bin/bash
# The GPU path of phm_torch in one run on a lent accelerator machine (torch, lightning, torchdiffeq, h5py there;
# nothing can be downloaded): the online step and the simulators against the same machine's CPU
# (scripts/bench_device.py), phm-train on the GPU and on the CPU, phm-generate device=cuda and a training on its store.
# Prepare here, once (both paths git-ignored, carried with the run):
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux2014_x86_64 -d .whl hydra-core==1.3.8 omegaconf==2.3.1
#   pip wheel --no-deps antlr4-python3-runtime==4.9.3 -w .whl     # an sdist on PyPI: a pure-Python wheel built here
#   phm-generate data_dir=.quick/store progress=false               # the small store the two trainings read
# Run: bash scripts/device_check.sh 2>&1 | tee $OUT/gpu.log  (carry .whl and .quick; about 9 minutes at most)
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
python3 -c "import torch, lightning, torchdiffeq, h5py, hydra; print('torch', torch.__version__, torch.cuda.is_available(), lightning.__version__)"
T0=$(date +%s)
el() { echo "=== $1 at +$(( $(date +%s) - T0 )) s"; }
el bench
timeout 180 python3 scripts/bench_device.py --device cuda --compile --out $OUT/bench_device.json 2>&1 | grep -v Warning
train() {  # $1 name, rest: overrides
  local n=$1; shift
  el "train $n"
  TIMEFORMAT="$n wall %R s"
  time timeout 60 python3 -m phm_torch.apps.train data_dir=.quick/store \
    trainer.enable_progress_bar=false out_dir=/tmp/tr_$n "$@" > /tmp/tr_$n.log 2>&1; echo "rc $?"
  tail -3 /tmp/tr_$n.log
  python3 - "$n" <<'PY'
import json, os, sys
n = sys.argv[1]
try:
    m = json.load(open(f"/tmp/tr_{n}/metrics.json"))
except OSError as e:
    sys.exit(f"{n}: no metrics ({e})")
print(n, "err_k", m.get("err_k"), "timing", json.dumps(m.get("timing")))
json.dump(m, open(os.environ["OUT"] + f"/train_{n}.json", "w"), indent=1)
PY
}
train gpu_lm trainer.accelerator=gpu classifier_refine.device=cuda
train cpu_lm trainer.accelerator=cpu threads=16
train gpu_adam model=fdi_adam trainer.accelerator=gpu classifier_refine.device=cuda
el generate
TIMEFORMAT="generate wall %R s"
time timeout 130 python3 -m phm_torch.apps.generate device=cuda data_dir=/tmp/g \
  dataset.n_train=2000 dataset.n_val=200 dataset.n_rul=16 dataset.chunk_size=2224 progress=false threads=16 > /tmp/gen.log 2>&1
echo "rc $?"; grep -v Warning /tmp/gen.log | tail -25; cp /tmp/gen.log $OUT/generate.log
if [ -f /tmp/g/dataset.h5 ]; then
  el "train on the generated store"
  TIMEFORMAT="train_gen wall %R s"
  time timeout 60 python3 -m phm_torch.apps.train data_dir=/tmp/g trainer.accelerator=gpu \
    classifier_refine.device=cuda trainer.enable_progress_bar=false out_dir=/tmp/tr_gen > /tmp/tr_gen.log 2>&1; echo "rc $?"
  cp /tmp/tr_gen/metrics.json $OUT/train_gen.json 2>/dev/null; grep -v Warning /tmp/tr_gen.log | tail -5
fi
el done
