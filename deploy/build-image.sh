#!/usr/bin/env bash
# Builds the mpiflow container image from deploy/Dockerfile.
#
#   deploy/build-image.sh [--tag mpiflow:latest] [--mode auto|registry|debootstrap]
#                         [--binary auto|build|prebuilt] [--rebuild-base] [--bases-only]
#                         [--ca-cert FILE|none]... [-- EXTRA DOCKER BUILD ARGS]
#
# Modes
#   registry     `docker build -f deploy/Dockerfile .` exactly as written: base images
#                debian:bookworm-slim and rust:1.95-slim-bookworm come from a registry.
#   debootstrap  for machines that reach Debian's package mirror but no image registry: the base
#                image is made here with `debootstrap --variant=minbase bookworm` + `docker
#                import` (tag mpiflow-base/debian:bookworm-slim, made once, reused) and handed to
#                the same Dockerfile as BASE_IMAGE/BUILDER_IMAGE build args. apt and pip inside the
#                build still need Debian's mirror and PyPI.
#   auto         registry when debian:bookworm-slim is present locally or can be pulled, else
#                debootstrap. (default)
#
# Binary (the Dockerfile's MPIFLOW_BINARY build arg)
#   build        cargo build --release inside the builder stage (clean, reproducible; slow on
#                a small machine). In debootstrap mode the builder base gets gcc, libc6-dev and a copy
#                of the host's Rust toolchain (`rustc --print sysroot`), since no toolchain can be
#                downloaded there; crates still come from crates.io during the build.
#   prebuilt     copy the host's target/release/mpiflow (run `cargo build --release` first). The
#                host's glibc must not be newer than bookworm's 2.36: the build runs the binary in
#                the base image and fails otherwise.
#   auto         registry mode: build; debootstrap mode: prebuilt when target/release/mpiflow
#                exists, else build. (default)
#
# CA certificates: the build downloads from PyPI (and crates.io with --binary build) over HTTPS.
# Where an HTTPS-intercepting proxy sits in between, its CA must be trusted inside the build:
# every *.crt under /usr/local/share/ca-certificates (where Debian keeps locally added CAs) is
# passed as the EXTRA_CA_CERTS build arg, used by the builder and ort stages only, never put in
# the runtime image. --ca-cert FILE (repeatable) names them instead; --ca-cert none passes none.
#
# Environment: MPIFLOW_DEBIAN_MIRROR (default http://deb.debian.org/debian), ORT_VERSION (1.31.1).
set -euo pipefail
cd "$(dirname "$0")/.."

TAG=mpiflow:latest
MODE=auto
BINARY=auto
REBUILD_BASE=0
BASES_ONLY=0
SUITE=bookworm
MIRROR=${MPIFLOW_DEBIAN_MIRROR:-http://deb.debian.org/debian}
ORT_VERSION=${ORT_VERSION:-1.31.1}
REGISTRY_BASE=debian:bookworm-slim
REGISTRY_BUILDER=rust:1.95-slim-bookworm
LOCAL_BASE=mpiflow-base/debian:${SUITE}-slim
LOCAL_BUILDER=mpiflow-base/rust:${SUITE}
EXTRA=()
CA_CERTS=()

while [ $# -gt 0 ]; do
  case "$1" in
    --tag) TAG=$2; shift 2 ;;
    --mode) MODE=$2; shift 2 ;;
    --binary) BINARY=$2; shift 2 ;;
    --rebuild-base) REBUILD_BASE=1; shift ;;
    --bases-only) BASES_ONLY=1; shift ;;
    --ca-cert) CA_CERTS+=("$2"); shift 2 ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    --) shift; EXTRA=("$@"); break ;;
    *) echo "build-image: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done

log() { printf '[build-image %4ss] %s\n' "$SECONDS" "$*" >&2; }
die() { log "error: $*"; exit 1; }

command -v docker >/dev/null || die "docker is not installed (Debian: apt-get install -y docker.io)"
docker info >/dev/null 2>&1 || die "no Docker daemon answers (start it: 'systemctl start docker' or 'dockerd &')"

# ------------------------------------------------------------------------------------ mode
if [ "$MODE" = auto ]; then
  if docker image inspect "$REGISTRY_BASE" >/dev/null 2>&1; then
    MODE=registry
  else
    log "probing the registry: docker pull $REGISTRY_BASE"
    if timeout 90 docker pull -q "$REGISTRY_BASE" >/dev/null 2>&1; then
      MODE=registry
    else
      MODE=debootstrap
      log "no image registry reachable: building on a debootstrap base"
    fi
  fi
fi
case "$MODE" in registry|debootstrap) ;; *) die "--mode must be auto, registry or debootstrap" ;; esac

if [ "$BINARY" = auto ]; then
  if [ "$MODE" = debootstrap ] && [ -x target/release/mpiflow ]; then BINARY=prebuilt; else BINARY=build; fi
fi
case "$BINARY" in build|prebuilt) ;; *) die "--binary must be auto, build or prebuilt" ;; esac

if [ "$BINARY" = prebuilt ]; then
  [ -x target/release/mpiflow ] || die "--binary prebuilt needs target/release/mpiflow: run 'cargo build --release' first"
  stale=$(find src proto build.rs Cargo.toml Cargo.lock -newer target/release/mpiflow -type f 2>/dev/null | head -n 3 || true)
  [ -z "$stale" ] || log "warning: target/release/mpiflow is older than: $(echo $stale) — rebuild it if that matters"
  if [ -r /etc/os-release ]; then
    host_os=$(. /etc/os-release; echo "${ID:-?} ${VERSION_CODENAME:-?}")
    [ "$host_os" = "debian $SUITE" ] || log "warning: host is '$host_os', the image is Debian $SUITE; a host binary linked against a newer glibc than 2.36 will not run there (the build checks)"
  fi
fi

# ------------------------------------------------------------------------------------ bases
debootstrap_rootfs() { # DIR [extra packages, comma separated]
  local dir=$1 include=ca-certificates${2:+,$2}
  [ "$(id -u)" = 0 ] || die "debootstrap needs root"
  command -v debootstrap >/dev/null || die "debootstrap is not installed (apt-get install -y debootstrap)"
  log "debootstrap --variant=minbase --include=$include $SUITE $dir $MIRROR"
  debootstrap --variant=minbase --include="$include" "$SUITE" "$dir" "$MIRROR" >"$dir.log" 2>&1 \
    || { tail -n 20 "$dir.log" >&2; die "debootstrap failed (log: $dir.log)"; }
  # Apt sources as in the official image: the release, its updates and the security archive.
  rm -f "$dir/etc/apt/sources.list"
  cat >"$dir/etc/apt/sources.list.d/debian.sources" <<EOF
Types: deb
URIs: $MIRROR
Suites: $SUITE $SUITE-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: http://deb.debian.org/debian-security
Suites: $SUITE-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
  # Slim like debian:*-slim: no docs, man pages or locales from later installs; apt cleans up.
  cat >"$dir/etc/dpkg/dpkg.cfg.d/docker-slim" <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
path-include /usr/share/locale/locale.alias
EOF
  cat >"$dir/etc/apt/apt.conf.d/docker-clean" <<'EOF'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache ""; Dir::Cache::srcpkgcache "";
Acquire::GzipIndexes "true";
EOF
  echo 'APT::Install-Recommends "false";' >"$dir/etc/apt/apt.conf.d/docker-no-recommends"
  find "$dir/usr/share/doc" -mindepth 2 ! -name copyright -delete 2>/dev/null || true
  rm -rf "$dir"/usr/share/man/* "$dir"/usr/share/info/* "$dir"/var/lib/apt/lists/* \
         "$dir"/var/cache/apt/* "$dir"/var/log/* "$dir"/tmp/* "$dir"/root/.cache
  : >"$dir/etc/hostname"; : >"$dir/etc/resolv.conf"
}

docker_import() { # DIR TAG [ENV...]
  local dir=$1 tag=$2; shift 2
  local changes=(--change 'CMD ["bash"]')
  local e; for e in "$@"; do changes+=(--change "ENV $e"); done
  log "docker import $tag"
  tar --numeric-owner --xattrs -C "$dir" --exclude='./proc/*' --exclude='./sys/*' --exclude='./dev/*' -cf - . \
    | docker import "${changes[@]}" --message "debootstrap $SUITE minbase (mpiflow deploy/build-image.sh)" - "$tag" >/dev/null
}

make_base() {
  if [ "$REBUILD_BASE" = 0 ] && docker image inspect "$LOCAL_BASE" >/dev/null 2>&1; then
    log "base $LOCAL_BASE exists (--rebuild-base to remake it)"; return
  fi
  local work; work=$(mktemp -d /var/tmp/mpiflow-base.XXXXXX)
  trap "rm -rf '$work' '$work.log'" EXIT
  debootstrap_rootfs "$work/rootfs"
  docker_import "$work/rootfs" "$LOCAL_BASE" 'PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin'
  rm -rf "$work"; trap - EXIT
}

make_builder_base() {
  if [ "$REBUILD_BASE" = 0 ] && docker image inspect "$LOCAL_BUILDER" >/dev/null 2>&1; then
    log "builder base $LOCAL_BUILDER exists (--rebuild-base to remake it)"; return
  fi
  command -v rustc >/dev/null || die "--binary build in debootstrap mode copies the host's Rust toolchain, and rustc is not on PATH"
  local sysroot; sysroot=$(rustc --print sysroot)
  [ -x "$sysroot/bin/cargo" ] || die "no cargo in the host toolchain $sysroot"
  local work; work=$(mktemp -d /var/tmp/mpiflow-builder.XXXXXX)
  trap "rm -rf '$work' '$work.log'" EXIT
  debootstrap_rootfs "$work/rootfs" gcc,libc6-dev
  log "copying the host Rust toolchain $sysroot ($(rustc --version)) into the builder base"
  mkdir -p "$work/rootfs/usr/local/rust" "$work/rootfs/usr/local/cargo"
  tar -C "$sysroot" --exclude=./share/doc --exclude=./lib/rustlib/src --exclude=./lib/rustlib/rustc-src -cf - . \
    | tar -C "$work/rootfs/usr/local/rust" -xf -
  docker_import "$work/rootfs" "$LOCAL_BUILDER" \
    'PATH=/usr/local/rust/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    'CARGO_HOME=/usr/local/cargo'
  rm -rf "$work"; trap - EXIT
}

if [ "$MODE" = registry ]; then
  BASE_IMAGE=$REGISTRY_BASE
  BUILDER_IMAGE=$REGISTRY_BUILDER
  # The builder stage only copies a file in prebuilt mode: no need for the Rust image then.
  [ "$BINARY" = prebuilt ] && BUILDER_IMAGE=$REGISTRY_BASE
else
  make_base
  BASE_IMAGE=$LOCAL_BASE
  if [ "$BINARY" = build ]; then make_builder_base; BUILDER_IMAGE=$LOCAL_BUILDER; else BUILDER_IMAGE=$LOCAL_BASE; fi
fi

if [ "$BASES_ONLY" = 1 ]; then
  log "bases ready (--bases-only): base=$BASE_IMAGE builder=$BUILDER_IMAGE"
  exit 0
fi

# ------------------------------------------------------------------------------------ build
if [ ${#CA_CERTS[@]} = 0 ] && [ -d /usr/local/share/ca-certificates ]; then
  while IFS= read -r f; do CA_CERTS+=("$f"); done \
    < <(find /usr/local/share/ca-certificates -name '*.crt' -type f | sort)
fi
EXTRA_CA_CERTS=
for f in ${CA_CERTS[@]+"${CA_CERTS[@]}"}; do
  [ "$f" = none ] && { EXTRA_CA_CERTS=; break; }
  [ -r "$f" ] || die "--ca-cert $f: not readable"
  EXTRA_CA_CERTS+="$(cat "$f")"$'\n'
  log "trusting $f in the build stages"
done
log "mode=$MODE binary=$BINARY base=$BASE_IMAGE builder=$BUILDER_IMAGE ort=$ORT_VERSION tag=$TAG"
t0=$SECONDS
docker build -f deploy/Dockerfile -t "$TAG" \
  --build-arg BASE_IMAGE="$BASE_IMAGE" \
  --build-arg BUILDER_IMAGE="$BUILDER_IMAGE" \
  --build-arg MPIFLOW_BINARY="$BINARY" \
  --build-arg ORT_VERSION="$ORT_VERSION" \
  --build-arg EXTRA_CA_CERTS="$EXTRA_CA_CERTS" \
  ${EXTRA[@]+"${EXTRA[@]}"} .
log "docker build took $((SECONDS - t0)) s; total $SECONDS s"
docker image ls "$TAG" >&2
