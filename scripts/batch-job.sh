#!/usr/bin/env bash
# One batch job: pull what a stage needs from the artifact store, run the stage's one
# `ede-pipeline` command, push what it made back. The same on the host and in the image, where it
# is installed as `batch-job`:
#
#   scripts/batch-job.sh STAGE [STAGE ...]
#   docker run --rm --user "$(id -u):$(id -g)" -v "$PWD":/work -v "$PWD/../ede-store":/ede-store \
#       --entrypoint batch-job ede train@ede/ReacherTurn-v0-td3-0
#
# STAGE is a name from `dvc stage list` (e.g. collect@reacher, pretrain_encoder@reacher,
# train@<task>-<algo>-<seed>); several are run one after the other, each as below (e.g.
# `task_code@reacher collect@reacher`: a stage's upstream stages must have run, here or in the store). The store is DVC's default remote: ../ede-store as
# committed in .dvc/config, or whatever `dvc remote default --local NAME` chose for this checkout.
# Run from the repository root (the container's /work).
#
#   1. pull:  the outputs of upstream stages that STAGE depends on (their hashes come from
#             dvc.lock), and the store's run cache;
#   2. run:   `dvc repro --single-item STAGE`, i.e. exactly the stage's `cmd` from dvc.yaml — or, if
#             this very run (same command, dependencies and params) is already in the store's run
#             cache, its outputs are checked out instead of computed again;
#   3. push:  the stage's outputs and its run-cache entry, which records the run (metrics and
#             plots included) so that `dvc repro --pull` anywhere restores it without rerunning.
#
# Jobs of a sweep (one per train stage) are independent and can run at the same time, each in
# its own checkout or all in one (DVC locks the paths each stage writes).
set -euo pipefail

[[ $# -ge 1 && $1 != -* ]] || { echo "usage: $(basename "$0") STAGE [STAGE ...]" >&2; exit 2; }

[[ -f dvc.yaml ]] || { echo "error: run from the repository root (no dvc.yaml in $PWD)" >&2; exit 2; }

for stage in "$@"; do
    echo "batch-job: $stage: pull, run, push" >&2
    dvc repro --pull --single-item "$stage"
    dvc push --run-cache "$stage"
done
