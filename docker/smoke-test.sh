#!/usr/bin/env bash
# docker/smoke-test.sh: build the modbus-gateway image, run it in demo mode (simulated
# RTU line, no hardware) and check from the host that
#   - a Modbus TCP request (FC03, unit 1, address 0, count 10) gets a normal response,
#   - GET /healthz answers 200 and the image's HEALTHCHECK command passes,
#   - the process runs as the unprivileged user, in the dialout group,
#   - it holds the compiled build (`modbus-gateway --version`),
#   - SIGTERM (docker/podman stop) ends it cleanly with exit code 0.
# Exits non-zero with a message naming the failed step; cleans up what it created.
#
# Engine: Docker when `docker info` answers; otherwise buildah + podman with a private
# vfs store (no daemon, no registry): Debian bookworm root file systems made with
# debootstrap (cached) stand in for the Dockerfile's base images (the builder's with gcc
# and the Python headers), and pip installs offline from wheels downloaded on the host.
#
# Environment:
#   SMOKE_ENGINE=docker|podman   force an engine (default: docker if it answers)
#   SMOKE_OFFLINE=0|1            build with --build-arg PIP_NO_INDEX=1 from host-downloaded
#                                wheels (default: 1 for podman, 0 for docker)
#   SMOKE_CACHE=DIR              where the rootfs tarball and wheels are cached
#                                (default: ${XDG_CACHE_HOME:-~/.cache}/modbus-gateway-smoke)
#   SMOKE_KEEP_IMAGE=1           keep the built image (docker) / store (podman)
#   SMOKE_TIMEOUT=SECONDS        how long to wait for the gateway to get ready (default 60)
set -Eeuo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
readonly REPO
readonly DOCKERFILE="$REPO/docker/Dockerfile"
readonly IMAGE="localhost/modbus-gateway:smoke"
readonly NAME="modbus-gateway-smoke-$$"
readonly CACHE="${SMOKE_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/modbus-gateway-smoke}"
readonly READY_TIMEOUT="${SMOKE_TIMEOUT:-60}"
readonly SUITE=bookworm

T0=$(date +%s)
STEP="start"
WORK=""
ENGINE=""
CONTAINER_STARTED=0

log() { printf 'smoke-test: %s\n' "$*" >&2; }
die() { trap - ERR; printf 'smoke-test: FAIL (%s): %s\n' "$STEP" "$*" >&2; exit 1; }
step() { STEP="$1"; log "[$(( $(date +%s) - T0 ))s] $1"; }

eng() { "$ENGINE" "$@"; }

cleanup() {
    local rc=$?
    trap - ERR
    set +e
    if [[ $CONTAINER_STARTED == 1 ]]; then
        if [[ $rc != 0 ]]; then
            log "container log (last 40 lines):"
            eng logs --tail 40 "$NAME" >&2 2>&1
        fi
        eng rm -f "$NAME" >/dev/null 2>&1
    fi
    if [[ $ENGINE == docker && ${SMOKE_KEEP_IMAGE:-0} != 1 ]]; then
        docker image rm -f "$IMAGE" >/dev/null 2>&1
    fi
    if [[ $ENGINE == podman && ${SMOKE_KEEP_IMAGE:-0} != 1 && -n $WORK ]]; then
        buildah rm --all >/dev/null 2>&1
        podman rm -af >/dev/null 2>&1
    fi
    if [[ -n $WORK ]]; then
        if [[ ${SMOKE_KEEP_IMAGE:-0} == 1 && $ENGINE == podman ]]; then
            log "store kept in $WORK (CONTAINERS_STORAGE_CONF=$WORK/storage.conf)"
        else
            rm -rf "$WORK"
        fi
    fi
    if [[ $rc == 0 ]]; then
        log "PASS in $(( $(date +%s) - T0 ))s (engine: $ENGINE)"
    else
        log "FAILED after $(( $(date +%s) - T0 ))s at step: $STEP"
    fi
    exit "$rc"
}
trap cleanup EXIT
trap 'die "command failed (exit $?): $BASH_COMMAND"' ERR

# An image the Dockerfile names by default (ARG PYTHON_IMAGE=..., ARG BUILDER_IMAGE=...),
# fully qualified.
image_arg() {
    local ref
    ref=$(sed -n "s/^ARG $1=//p" "$DOCKERFILE" | head -n1)
    [[ -n $ref ]] || die "no 'ARG $1=' default in $DOCKERFILE"
    case "$ref" in
        */*/*|*.*/*|localhost/*) printf '%s\n' "$ref" ;;
        */*) printf 'docker.io/%s\n' "$ref" ;;
        *) printf 'docker.io/library/%s\n' "$ref" ;;
    esac
}

# Copy of the build context: the work tree's tracked and untracked (not ignored)
# files, so the build sees exactly what is on disk without writing into the repo.
make_context() {
    local ctx="$WORK/context"
    mkdir -p "$ctx"
    # Files deleted in the work tree but still in the index are left out.
    # shellcheck disable=SC2016  # $f is expanded by the inner sh
    (cd "$REPO" && git ls-files -z --cached --others --exclude-standard \
        | xargs -0 -r sh -c 'for f; do [ -e "$f" ] && printf "%s\0" "$f"; done' sh \
        | tar --null -T - -cf -) | tar -C "$ctx" -xf -
    [[ -f $ctx/pyproject.toml && -d $ctx/gateway ]] || die "build context incomplete in $ctx"
    printf '%s\n' "$ctx"
}

# Wheels for an offline build: the build backend and the runtime dependencies named
# in pyproject.toml, for CPython 3.11 on this architecture.
download_wheels() {
    local dest="$1" arch
    arch=$(uname -m)
    mkdir -p "$CACHE/wheels"
    mapfile -t reqs < <(python3 - "$REPO/pyproject.toml" <<'PY'
import sys, tomllib
with open(sys.argv[1], "rb") as f:
    data = tomllib.load(f)
for req in data["build-system"]["requires"] + data["project"].get("dependencies", []):
    print(req)
PY
)
    log "downloading wheels: ${reqs[*]}"
    python3 -m pip download --quiet --disable-pip-version-check \
        --dest "$CACHE/wheels" --only-binary=:all: \
        --python-version 3.11 --implementation cp \
        --platform "manylinux2014_$arch" --platform "manylinux_2_17_$arch" \
        --platform "manylinux_2_28_$arch" --platform "manylinux_2_31_$arch" \
        "${reqs[@]}" \
        || die "pip download of the build's wheels failed (is a package index reachable from the host?)"
    cp "$CACHE"/wheels/*.whl "$dest"/
}

# ------------------------------------------------------------------------- engines
build_with_docker() {
    local ctx="$1" offline="$2"
    step "docker build"
    local args=(-f "$ctx/docker/Dockerfile" -t "$IMAGE")
    [[ $offline == 1 ]] && args+=(--build-arg PIP_NO_INDEX=1)
    docker build "${args[@]}" "$ctx" || die "docker build failed"
}

setup_podman() {
    step "podman/buildah setup"
    local missing=()
    for tool in podman buildah debootstrap runc; do
        command -v "$tool" >/dev/null || missing+=("$tool")
    done
    if (( ${#missing[@]} )); then
        [[ $(id -u) == 0 ]] || die "missing ${missing[*]}; install them (apt-get install podman buildah debootstrap runc) or run as root"
        log "installing ${missing[*]}"
        DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
            podman buildah debootstrap runc >/dev/null \
            || die "apt-get install podman buildah debootstrap runc failed"
    fi
    [[ $(id -u) == 0 ]] || die "the podman path runs rootful (chroot isolation, vfs store): run as root"
    # A private store and engine settings, so the host's containers are untouched.
    cat >"$WORK/storage.conf" <<EOF
[storage]
driver = "vfs"
graphroot = "$WORK/storage"
runroot = "$WORK/run"
EOF
    cat >"$WORK/containers.conf" <<EOF
[engine]
cgroup_manager = "cgroupfs"
events_logger = "file"
runtime = "runc"
EOF
    export CONTAINERS_STORAGE_CONF="$WORK/storage.conf"
    export CONTAINERS_CONF="$WORK/containers.conf"
    export BUILDAH_ISOLATION=chroot
}

# Debian bookworm root file systems standing in for the base images: the same Debian release
# and Python minor version as python:3.11-slim-bookworm (the runtime: python3 and its venv
# module) and python:3.11-bookworm (the builder: with gcc and the Python headers too).
readonly RUNTIME_PACKAGES=python3,python3-venv,ca-certificates
readonly BUILDER_PACKAGES=$RUNTIME_PACKAGES,gcc,libc6-dev,python3-dev
import_base_image() {
    local image="$1" packages="$2" name="$3" tarball="$CACHE/$SUITE-$3-rootfs.tar"
    if [[ ! -s $tarball ]]; then
        step "debootstrap $SUITE rootfs with $packages (cached afterwards in $tarball)"
        local rootfs="$WORK/rootfs-$name"
        debootstrap --variant=minbase --include="$packages" \
            "$SUITE" "$rootfs" >"$WORK/debootstrap.log" 2>&1 \
            || { tail -n 20 "$WORK/debootstrap.log" >&2; die "debootstrap failed"; }
        rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
        mkdir -p "$CACHE"
        tar -C "$rootfs" -cf "$tarball.tmp" . && mv "$tarball.tmp" "$tarball"
        rm -rf "$rootfs"
    fi
    step "import base image as $image"
    podman import --quiet "$tarball" "localhost/modbus-gateway-smoke-$name:$SUITE" >/dev/null \
        || die "podman import failed"
    podman tag "localhost/modbus-gateway-smoke-$name:$SUITE" "$image"
}

build_with_buildah() {
    local ctx="$1" offline="$2"
    step "buildah bud"
    local args=(--isolation chroot --storage-driver vfs --pull=never --format docker
                --layers=false -f "$ctx/docker/Dockerfile" -t "$IMAGE")
    [[ $offline == 1 ]] && args+=(--build-arg PIP_NO_INDEX=1)
    buildah bud "${args[@]}" "$ctx" || die "buildah bud failed"
}

# ------------------------------------------------------------------------- checks
run_container() {
    step "run the image in demo mode"
    local args=(run -d --name "$NAME" -p 127.0.0.1::5020 -p 127.0.0.1::9502)
    # runc (crun fails in some sandboxes); podman's default rlimits (nofile, nproc
    # 1048576) may exceed what an unprivileged sandbox lets runc set: ask for less.
    [[ $ENGINE == podman ]] && args+=(--runtime runc --ulimit nofile=4096:4096
                                      --ulimit nproc=4096:4096)
    # Podman without systemd complains on stderr that it cannot add healthcheck timers
    # (harmless); keep that out of the output unless the run fails.
    eng "${args[@]}" "$IMAGE" --demo --listen 0.0.0.0:5020 --metrics 0.0.0.0:9502 \
        >/dev/null 2>"$WORK/run.err" || { cat "$WORK/run.err" >&2; die "$ENGINE run failed"; }
    CONTAINER_STARTED=1
}

host_port() {
    # `docker port NAME 5020/tcp` prints e.g. 127.0.0.1:49153
    local out
    out=$(eng port "$NAME" "$1/tcp" | head -n1)
    [[ $out =~ :([0-9]+)$ ]] || die "no host port published for $1/tcp (got '$out')"
    printf '%s\n' "${BASH_REMATCH[1]}"
}

wait_ready() {
    step "wait for 'listening on' (<= ${READY_TIMEOUT}s)"
    local deadline=$(( $(date +%s) + READY_TIMEOUT ))
    while :; do
        if eng logs "$NAME" 2>&1 | grep -q 'listening on'; then
            return 0
        fi
        local state
        state=$(eng inspect --format '{{.State.Status}}' "$NAME" 2>/dev/null || echo gone)
        [[ $state == running || $state == created ]] \
            || die "container is $state before it was ready"
        (( $(date +%s) < deadline )) || die "no 'listening on' line within ${READY_TIMEOUT}s"
        sleep 0.5
    done
}

check_modbus_and_health() {
    local mb_port="$1" http_port="$2"
    step "Modbus TCP FC03 on 127.0.0.1:$mb_port, /healthz on 127.0.0.1:$http_port"
    python3 - "$mb_port" "$http_port" <<'PY' || die "Modbus TCP or /healthz check failed"
import socket, struct, sys, time, urllib.request

mb_port, http_port = int(sys.argv[1]), int(sys.argv[2])
deadline = time.monotonic() + 20

def retrying(what, fn):
    """The published port may take a moment to forward; retry until the deadline."""
    while True:
        try:
            return fn()
        except (OSError, ValueError) as exc:
            if time.monotonic() > deadline:
                sys.exit(f"{what}: {exc!r}")
            time.sleep(0.3)

def recv_exact(sock, n):
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ValueError(f"connection closed after {len(buf)} of {n} bytes")
        buf += chunk
    return buf

def modbus():
    tid, unit, count = 0x5A17, 1, 10
    request = struct.pack(">HHHBBHH", tid, 0, 6, unit, 0x03, 0, count)
    with socket.create_connection(("127.0.0.1", mb_port), timeout=5) as sock:
        sock.sendall(request)
        header = recv_exact(sock, 7)
        r_tid, r_proto, r_len, r_unit = struct.unpack(">HHHB", header)
        pdu = recv_exact(sock, r_len - 1)
    if (r_tid, r_proto, r_unit) != (tid, 0, unit):
        raise ValueError(f"bad MBAP header {header.hex(' ')}")
    if pdu[0] != 0x03:
        raise ValueError(f"not a normal FC03 response: {pdu.hex(' ')}")
    if pdu[1] != 2 * count or len(pdu) != 2 + 2 * count:
        raise ValueError(f"byte count {pdu[1]} / length {len(pdu)} != {2 * count}: {pdu.hex(' ')}")
    return struct.unpack(f">{count}H", pdu[2:])

def healthz():
    with urllib.request.urlopen(f"http://127.0.0.1:{http_port}/healthz", timeout=5) as resp:
        if resp.status != 200:
            raise ValueError(f"/healthz status {resp.status}")
        return resp.read(200)

print("smoke-test: FC03 registers:", retrying("Modbus FC03", modbus), file=sys.stderr)
print("smoke-test: /healthz:", retrying("/healthz", healthz), file=sys.stderr)
PY
}

check_inside() {
    step "HEALTHCHECK command and user inside the container"
    # Run the Dockerfile's own HEALTHCHECK command (the interval is too long to wait for).
    local hc=()
    mapfile -d '' -t hc < <(python3 - "$DOCKERFILE" <<'PY'
import json, re, sys
text = open(sys.argv[1]).read().replace("\\\n", " ")
m = re.search(r"^HEALTHCHECK\b.*?\bCMD\s+(\[.*\])\s*$", text, re.M)
sys.stdout.write("".join(arg + "\0" for arg in json.loads(m.group(1))) if m else "")
PY
)
    (( ${#hc[@]} )) || die "no exec-form HEALTHCHECK CMD found in the Dockerfile"
    eng exec "$NAME" "${hc[@]}" || die "the HEALTHCHECK command fails inside the container: ${hc[*]}"
    if [[ $ENGINE == podman ]]; then
        # Also proves the built image kept its HEALTHCHECK (docker format, not OCI).
        podman healthcheck run "$NAME" || die "podman healthcheck run: unhealthy or no HEALTHCHECK in the image"
    fi
    local ids
    ids=$(eng exec "$NAME" id)
    log "id: $ids"
    [[ $ids != uid=0\(* ]] || die "the gateway runs as root"
    [[ $ids == *"(dialout)"* ]] || die "the gateway's user is not in the dialout group"
}

check_build() {
    step "the image holds the compiled build"
    local version
    version=$(eng exec "$NAME" modbus-gateway --version) || die "modbus-gateway --version failed"
    log "$version"
    [[ $version == *"(compiled)"* ]] \
        || die "not the compiled build: '$version' (does the builder image have gcc?)"
}

check_stop() {
    step "SIGTERM stops the gateway with exit code 0"
    eng stop -t 15 "$NAME" >/dev/null 2>"$WORK/stop.err" \
        || { cat "$WORK/stop.err" >&2; die "$ENGINE stop failed"; }
    local code
    code=$(eng inspect --format '{{.State.ExitCode}}' "$NAME")
    [[ $code == 0 ]] || die "exit code $code after SIGTERM (137 = killed after the stop timeout: no SIGTERM handling as PID 1)"
    eng logs "$NAME" 2>&1 | tail -n 5 >&2 || true
}

# ------------------------------------------------------------------------- main
main() {
    [[ -f $DOCKERFILE ]] || die "$DOCKERFILE not found"
    command -v python3 >/dev/null || die "python3 is needed on the host"
    WORK=$(mktemp -d "${TMPDIR:-/tmp}/modbus-gateway-smoke.XXXXXX")
    mkdir -p "$CACHE"

    ENGINE="${SMOKE_ENGINE:-}"
    if [[ -z $ENGINE ]]; then
        if command -v docker >/dev/null && docker info >/dev/null 2>&1; then
            ENGINE=docker
        else
            ENGINE=podman
        fi
    fi
    if [[ $ENGINE == docker ]] && ! docker info >/dev/null 2>&1; then
        die "no Docker engine answers 'docker info' (SMOKE_ENGINE=docker)"
    fi
    local offline="${SMOKE_OFFLINE:-}"
    [[ -n $offline ]] || { [[ $ENGINE == podman ]] && offline=1 || offline=0; }
    log "engine: $ENGINE, offline pip: $offline, cache: $CACHE"

    step "assemble build context"
    local ctx
    ctx=$(make_context)
    if [[ $offline == 1 ]]; then
        step "download wheels for an offline build"
        download_wheels "$ctx/docker/wheels"
    fi

    case "$ENGINE" in
        docker)
            build_with_docker "$ctx" "$offline"
            ;;
        podman)
            setup_podman
            import_base_image "$(image_arg PYTHON_IMAGE)" "$RUNTIME_PACKAGES" python3
            import_base_image "$(image_arg BUILDER_IMAGE)" "$BUILDER_PACKAGES" python3-gcc
            build_with_buildah "$ctx" "$offline"
            ;;
        *) die "unknown SMOKE_ENGINE=$ENGINE (docker or podman)" ;;
    esac
    local t_built=$(( $(date +%s) - T0 ))

    run_container
    wait_ready
    check_modbus_and_health "$(host_port 5020)" "$(host_port 9502)"
    check_inside
    check_build
    check_stop
    log "image built in ${t_built}s; run checks in $(( $(date +%s) - T0 - t_built ))s"
}

main "$@"
