#!/usr/bin/env bash
# The GPU check: on a machine with an NVIDIA GPU, set up from the project's own files, then run
# `python -m bench.gpu` (CUDA tests, bench.learner --device cuda, a 3-minute nasa up) and print
# its one JSON line last. Without a GPU it says so in one line, runs nothing and exits 0.
#
#   scripts/gpu-check.sh
#   NASA_WHEELS=DIR scripts/gpu-check.sh   # offline: the requirements this machine's Python
#                                          # lacks come from wheels in DIR (pip --no-index)
#   PYTHONPATH=SITE scripts/gpu-check.sh   # offline: the machine's own python3 (its CUDA torch)
#                                          # with the rest unpacked in SITE; no setup at all
#
# The Python it uses is the first that sees the GPU and imports every requirement the check
# needs (`python -m bench.gpu missing` prints nothing): $NASA_PYTHON if set, .venv, .venv-gpu,
# then the machine's python3; only when none does is one set up.
#
# Everything is bounded: the whole script by TOTAL_TIMEOUT_S (default 540 s, setup included),
# setup by SETUP_TIMEOUT_S, nvidia-smi by SMI_TIMEOUT_S (a stuck driver: one line, exit 1), and
# each step of the check by its own timeout, so it ends in time even when something hangs.
set -uo pipefail
cd "$(dirname "$0")/.."

SMI_TIMEOUT_S=${SMI_TIMEOUT_S:-30}  # a stuck driver leaves nvidia-smi waiting for ever
GPU_LINE=""
if command -v nvidia-smi >/dev/null 2>&1; then
    GPU_LINE=$(timeout -k 5 "$SMI_TIMEOUT_S" nvidia-smi -L 2>/dev/null)
    rc=$?
    if [ $rc -eq 124 ] || [ $rc -eq 137 ]; then
        echo "gpu-check: nvidia-smi did not answer within ${SMI_TIMEOUT_S} s (a stuck GPU driver?); nothing was run" >&2
        exit 1
    fi
    [ $rc -eq 0 ] || GPU_LINE=""
fi
if [ -z "$GPU_LINE" ]; then
    echo "gpu-check: needs a machine with an NVIDIA GPU (no nvidia-smi or no GPU here); nothing was run"
    exit 0
fi

TOTAL_TIMEOUT_S=${TOTAL_TIMEOUT_S:-540}
SETUP_TIMEOUT_S=${SETUP_TIMEOUT_S:-120}
export MUJOCO_GL=${MUJOCO_GL:-egl}
export PYTHONUNBUFFERED=1

cuda_python() {  # a Python whose torch sees the GPU and which imports every requirement
    [ -x "$1" ] || command -v "$1" >/dev/null 2>&1 || return 1
    timeout 60 "$1" -c 'import torch, sys; sys.exit(not torch.cuda.is_available())' 2>/dev/null &&
        [ -z "$(timeout 60 "$1" -m bench.gpu missing 2>/dev/null || echo unknown)" ]
}

PY=""
for candidate in ${NASA_PYTHON:-} .venv/bin/python .venv-gpu/bin/python python3; do
    if cuda_python "$candidate"; then PY=$candidate; break; fi
done
if [ -z "$PY" ]; then
    if [ -n "${NASA_WHEELS:-}" ]; then
        # Offline: a venv over the machine's Python (its CUDA torch), the missing pins from wheels.
        BASE=${PYTHON:-python3}
        echo "gpu-check: setup: .venv-gpu over $($BASE -c 'import sys; print(sys.executable)') with wheels from $NASA_WHEELS"
        timeout "$SETUP_TIMEOUT_S" "$BASE" -m venv --system-site-packages .venv-gpu || exit 1
        MISSING=$(.venv-gpu/bin/python -m bench.gpu missing)
        if [ -n "$MISSING" ]; then
            # shellcheck disable=SC2086  # one argument per requirement
            timeout "$SETUP_TIMEOUT_S" .venv-gpu/bin/python -m pip install -q --disable-pip-version-check \
                --no-index --find-links "$NASA_WHEELS" $MISSING || { echo "gpu-check: setup failed" >&2; exit 1; }
        fi
        PY=.venv-gpu/bin/python
    else
        echo "gpu-check: setup: scripts/setup.sh"
        timeout "$SETUP_TIMEOUT_S" scripts/setup.sh || { echo "gpu-check: setup failed (scripts/setup.sh)" >&2; exit 1; }
        PY=.venv/bin/python
    fi
    if ! cuda_python "$PY"; then
        echo "gpu-check: after setup, $PY still lacks CUDA or a requirement: $("$PY" -m bench.gpu missing 2>&1)" >&2
        exit 1
    fi
fi

echo "gpu-check: $PY, torch $("$PY" -c 'import torch; print(torch.__version__)'), $(echo "$GPU_LINE" | head -1)"
CHECK_TIMEOUT_S=$((TOTAL_TIMEOUT_S - SECONDS - 20))
if [ "$CHECK_TIMEOUT_S" -lt 120 ]; then
    echo "gpu-check: setup took ${SECONDS} s; too little of the ${TOTAL_TIMEOUT_S} s is left for the check" >&2
    exit 1
fi
timeout -k 15 "$CHECK_TIMEOUT_S" "$PY" -m bench.gpu --budget-s $((CHECK_TIMEOUT_S - 30)) "$@"
