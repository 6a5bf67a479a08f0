#!/usr/bin/env bash
# The image, tested for real on a machine with no Docker engine and no reachable registry
# (the recipe of README.md, "Building the image without a Docker engine"): build the Dockerfile
# with rootful podman, run `ede-pipeline envs`, a tiny `collect` and a batch job in it against a
# scratch copy of this repo mounted from the host, check what they wrote from the host side, then
# run the README's `docker` lines through the docker client against podman's socket.
#
# Needs root (it installs podman, runc and debootstrap with apt when missing) and the project's
# .venv (`make install`). State (podman storage, the base image) lives in $EDE_PODMAN_DIR,
# default /var/tmp/ede-podman, so a second run reuses the layers.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
state=${EDE_PODMAN_DIR:-/var/tmp/ede-podman}
venv=${VENV:-.venv}
python=$repo/$venv/bin/python
start=$SECONDS
step() { printf '\n== [%4ss] %s\n' "$((SECONDS - start))" "$*"; }
fail() { echo "container-test: FAIL: $*" >&2; exit 1; }

[[ $(id -u) == 0 ]] || fail "run as root (rootful podman)"
[[ -x $python ]] || fail "$python missing: run 'make install' first"

step "tools: podman, runc, debootstrap"
missing=()
for tool in podman runc debootstrap; do command -v "$tool" >/dev/null || missing+=("$tool"); done
if ((${#missing[@]})); then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        podman runc debootstrap >/dev/null
fi
command -v docker >/dev/null || fail "no docker client on PATH"

# Host quirks: the open-files hard limit is below what podman asks for, and crun refuses the
# host's hybrid cgroups. Host networking: no bridge setup, and the same for `docker run`.
mkdir -p "$state"
cat >"$state/containers.conf" <<'CONF'
[containers]
default_ulimits = ["nofile=20000:20000", "nproc=32768:32768"]
netns = "host"
[engine]
runtime = "runc"
CONF
export CONTAINERS_CONF=$state/containers.conf
storage=(--root "$state/storage" --runroot "$state/run" --storage-driver overlay)
pm() { podman "${storage[@]}" "$@"; }

step "base image: debian:bookworm-slim from debootstrap (nothing can be pulled)"
base=docker.io/library/debian:bookworm-slim
if ! pm image exists "$base"; then
    mirror=$(sed -n 's/^URIs: *//p' /etc/apt/sources.list.d/*.sources 2>/dev/null | tr ' ' '\n' \
        | grep -E '/debian/?$' | head -n1 || true)
    [[ -n $mirror ]] || mirror=$(awk '$1 == "deb" && $3 == "bookworm" {print $2; exit}' \
        /etc/apt/sources.list 2>/dev/null || true)
    mirror=${mirror:-http://deb.debian.org/debian}
    rootfs=$(mktemp -d "$state/rootfs.XXXX")
    nice -n 10 debootstrap --variant=minbase bookworm "$rootfs" "$mirror" >"$state/debootstrap.log" \
        || { tail -20 "$state/debootstrap.log"; fail "debootstrap"; }
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    tar -C "$rootfs" -c . | pm import - localhost/debian:bookworm >/dev/null
    pm tag localhost/debian:bookworm "$base"
    rm -rf "$rootfs"
fi

step "torch wheel for the image: the locked CPU build (its hash checked), into docker/wheels/"
if ! ls docker/wheels/torch-"$("$python" scripts/lock.py version requirements.lock torch)"-*.whl \
        >/dev/null 2>&1; then
    "$python" scripts/lock.py select requirements.lock --only torch >"$state/torch.lock"
    "$python" -m pip download --quiet --no-deps --require-hashes --dest docker/wheels \
        -r "$state/torch.lock"
fi

step "build (podman, host CA for the build's HTTPS)"
pipconf=$state/pip.conf
printf '[global]\ncert = /etc/ssl/host-ca.crt\n' >"$pipconf"
build_start=$SECONDS
nice -n 10 podman "${storage[@]}" build --pull=never --network host \
    --build-arg EDE_COMMIT="$(git rev-parse HEAD)" \
    -v /etc/ssl/certs/ca-certificates.crt:/etc/ssl/host-ca.crt:ro -v "$pipconf:/etc/pip.conf:ro" \
    -t localhost/ede:latest -t docker.io/library/ede:latest . >"$state/build.log" 2>&1 \
    || { tail -40 "$state/build.log"; fail "podman build"; }
echo "build: $((SECONDS - build_start)) s; image: $(pm image inspect --format '{{.Size}}' localhost/ede \
    | awk '{printf "%.0f MB", $1 / 1e6}')"

# A scratch copy of the repo (tracked and untracked-but-not-ignored files), tiny params.
work=$(mktemp -d /var/tmp/ede-container-test.XXXX)
podman_pid=
cleanup() {
    [[ -n $podman_pid ]] && kill "$podman_pid" 2>/dev/null && wait "$podman_pid" 2>/dev/null
    rm -rf "$work"
}
trap cleanup EXIT
copy_repo() {  # copy_repo DEST
    mkdir -p "$1"
    git ls-files -z --cached --others --exclude-standard \
        | (while IFS= read -r -d '' f; do [[ -f $f ]] && printf '%s\0' "$f"; done) \
        | xargs -0 cp --parents --preserve=mode,timestamps -t "$1"
    "$python" - "$1/params.yaml" <<'PY'
import sys, yaml
path = sys.argv[1]
params = yaml.safe_load(open(path))
params["collect"].update(steps=200, num_envs=1)
# A TD3 run small enough to train in seconds, for the video step.
params["td3"].update(hidden=[16, 16], batch_size=32, start_steps=50, eval_every=100,
                     eval_episodes=1, checkpoint_every=1000, buffer_size=1000)
params["runs"]["budgets"]["ede/ReacherVertical-v0"] = 200
open(path, "w").write(yaml.safe_dump(params, sort_keys=False))
PY
    git -C "$1" init -q && git -C "$1" add -A
    git -C "$1" -c user.name=ci -c user.email=ci@localhost commit -q -m scratch
}
check_store() {  # check_store REPO: the tiny collect's store, read by the host's library
    "$python" - "$1/data/families/point/rollouts.zarr" <<'PY'
import sys
from ede.io.rollouts import Rollouts
rollouts = Rollouts.open(sys.argv[1], env_id="ede/Point-v0")
assert len(rollouts) == 200, len(rollouts)
print(f"host reads {sys.argv[1]}: {len(rollouts)} steps, fingerprint ok")
PY
}

step "podman run as the image's own user (uid 1000): envs, collect"
copy_repo "$work/podman/repo"
chown -R 1000:1000 "$work/podman"
run=(run --rm -v "$work/podman/repo":/work -v "$work/podman/ede-store":/ede-store)
mkdir -p "$work/podman/ede-store" && chown 1000:1000 "$work/podman/ede-store"
pm "${run[@]}" localhost/ede envs | tee "$work/envs.txt"
grep -q 'ede/Point-v0' "$work/envs.txt" || fail "envs does not list ede/Point-v0"
pm "${run[@]}" localhost/ede collect --family point --out data/families/point/rollouts.zarr
check_store "$work/podman/repo"
[[ $(stat -c %u "$work/podman/repo/data/families/point/rollouts.zarr") == 1000 ]] || fail "not written by uid 1000"
pm "${run[@]}" --entrypoint python localhost/ede -c '
import gymnasium as gym, numpy as np
env = gym.make("ede_envs:ede/ReacherTurn-v0", render_mode="rgb_array"); env.reset(seed=0)
frame = env.render(); assert frame.ndim == 3 and frame.std() > 0, frame.shape
print("headless render (MUJOCO_GL=egl):", frame.shape)'
pm "${run[@]}" --entrypoint python localhost/ede -c '
import torch
from ede.run.group import compile_mode, compiler_missing, COMPILE_FROM_UPDATES
cpu = torch.device("cpu")
assert compiler_missing(cpu) is None, compiler_missing(cpu)
assert compile_mode("auto", COMPILE_FROM_UPDATES, cpu) == "default"
x = torch.randn(64)
assert torch.allclose(torch.compile(lambda v: torch.relu(v) * 2 + 1)(x), torch.relu(x) * 2 + 1)
print("torch.compile on the CPU: g++ and Python.h present, a kernel compiled and run")'
pm "${run[@]}" localhost/ede train --task ede/ReacherVertical-v0 --algo td3 --seed 0
pm "${run[@]}" localhost/ede render data/runs/ede/ReacherVertical-v0/td3/seed0 --out data/clip.mp4
[[ $(stat -c %s "$work/podman/repo/data/clip.mp4") -gt 10000 ]] || fail "render wrote no video"

step "podman run: a batch job (pull, run, push) into the default store ../ede-store"
rm -rf "$work/podman/repo/data"
pm "${run[@]}" --entrypoint batch-job localhost/ede task_code@point collect@point
check_store "$work/podman/repo"
ls "$work/podman/ede-store/files/md5" >/dev/null || fail "nothing pushed to ../ede-store"
# The host side: the same store, nothing stale, and the same artifact `dvc repro` makes here.
(cd "$work/podman/repo" && PATH=$repo/$venv/bin:$PATH dvc status --quiet collect@point) || fail "dvc status not clean"
copy_repo "$work/host/repo"
(cd "$work/host/repo" && PATH=$repo/$venv/bin:$PATH dvc repro --quiet collect@point)
# The same store: every array byte for byte and every attribute, except the recorded software
# versions, which name what made each (Debian's Python in the image, the host's Python here).
same_store() {  # same_store REPO_A REPO_B
    "$python" - "$1/data/families/point/rollouts.zarr" "$2/data/families/point/rollouts.zarr" <<'PY'
import sys
from ede.io.provenance import describe_software
from ede.io.rollouts import Rollouts
a, b = (Rollouts.open(path) for path in sys.argv[1:3])
arrays_a, arrays_b = a.arrays(), b.arrays()
assert arrays_a.keys() == arrays_b.keys(), (sorted(arrays_a), sorted(arrays_b))
for name, array in arrays_a.items():
    other = arrays_b[name]
    assert array.dtype == other.dtype and array.shape == other.shape and array.tobytes() == other.tobytes(), \
        f"array {name} differs"
attrs_a, attrs_b = ({k: v for k, v in r.attrs.items() if k != "software"} for r in (a, b))
assert attrs_a == attrs_b, {k: (attrs_a.get(k), attrs_b.get(k)) for k in attrs_a.keys() | attrs_b.keys()
                            if attrs_a.get(k) != attrs_b.get(k)}
print(f"byte-identical arrays and attributes, fingerprint {a.attrs['fingerprint'][:16]}")
for path, r in zip(sys.argv[1:3], (a, b)):
    print(f"  made with {describe_software(r.attrs.get('software'))}: {path}")
PY
}
same_store "$work/podman/repo" "$work/host/repo" || fail "the container's store differs from the host's dvc repro"

step "docker client against podman's socket: the README's lines as written"
socket=$state/podman.sock
rm -f "$socket"
podman "${storage[@]}" system service --time=0 "unix://$socket" &
podman_pid=$!
for _ in $(seq 50); do [[ -S $socket ]] && break; sleep 0.2; done
export DOCKER_HOST=unix://$socket
copy_repo "$work/docker/repo"
cd "$work/docker/repo"
# --- as in README.md, "Batch jobs" (the image: built above by podman as `ede`; the README's
# `docker build -t ede .` cannot run as written here, since a build's HTTPS needs the proxy's CA
# and podman's Docker API does not reuse the layers of the podman build) ---
envs=$(docker run --rm --user "$(id -u):$(id -g)" -v "$PWD":/work ede envs) || fail "docker run ede envs"
grep -q 'ede/Point-v0' <<<"$envs" || fail "docker run ede envs: no ede/Point-v0 in its list"
docker run --rm --user "$(id -u):$(id -g)" -v "$PWD":/work ede collect --family point --out data/families/point/rollouts.zarr
check_store "$PWD"
rm -rf data
mkdir -p ../ede-store
docker run --rm --user "$(id -u):$(id -g)" -v "$PWD":/work -v "$PWD/../ede-store":/ede-store \
    --entrypoint batch-job ede task_code@point collect@point
# ---
check_store "$PWD"
same_store "$PWD" "$work/host/repo" || fail "docker batch job differs from dvc repro"
PATH=$repo/$venv/bin:$PATH dvc status --quiet collect@point || fail "dvc status not clean after the docker batch job"
cd "$repo"

step "container test passed in $((SECONDS - start)) s"
