#!/usr/bin/env bash
# Builds the hac runtime image without a container registry: a Debian base made with debootstrap
# from Debian's packages and `docker import`, then the release binaries built here layered on it
# (deploy/docker/Dockerfile.local). The image is the same as deploy/docker/Dockerfile's runtime
# stage: /usr/local/bin/{hac,hac-learner,hac-actor}, user hac (uid/gid 10001), /var/lib/hac.
#
#   deploy/docker/build-local.sh                 # builds hac:latest
#   HAC_IMAGE=hac:dev deploy/docker/build-local.sh
#
# Needs docker, debootstrap (apt-get install debootstrap; run as root, it makes the root
# filesystem) and a Rust toolchain. Variables:
#   HAC_IMAGE        the image to build (default hac:latest)
#   HAC_BASE_IMAGE   the base image (default hac-base:bookworm); imported when missing
#   HAC_BINARIES     a directory holding hac, hac-learner and hac-actor already built: no cargo
#   DEBIAN_MIRROR    the Debian archive (default: the first one in the apt sources)
# The base's root filesystem is cached as a tarball in ${XDG_CACHE_HOME:-$HOME/.cache}/hac-ci/,
# so only the first build runs debootstrap. The binaries need the glibc of the machine that built
# them: the base is Debian 12 (bookworm); build on bookworm or older.
set -euo pipefail

repo=$(cd "$(dirname "$0")/../.." && pwd)
image=${HAC_IMAGE:-hac:latest}
base=${HAC_BASE_IMAGE:-hac-base:bookworm}
suite=bookworm
cache="${XDG_CACHE_HOME:-$HOME/.cache}/hac-ci"
tarball="$cache/rootfs-$suite-minbase.tar"

die() {
    echo "build-local: $*" >&2
    exit 1
}

command -v docker >/dev/null || die "docker is not on PATH"
docker info >/dev/null 2>&1 || die "cannot talk to the Docker engine (docker info fails)"

# ---- the base: debootstrap once (cached tarball), docker import when the image is missing
if ! docker image inspect "$base" >/dev/null 2>&1; then
    if [ ! -s "$tarball" ]; then
        command -v debootstrap >/dev/null || [ -x /usr/sbin/debootstrap ] ||
            die "debootstrap is missing (apt-get install debootstrap)"
        [ "$(id -u)" = 0 ] || die "debootstrap must run as root to make the base's root filesystem"
        mirror=${DEBIAN_MIRROR:-$(
            {
                grep -hE '^URIs:' /etc/apt/sources.list.d/*.sources 2>/dev/null |
                    awk '{ for (i = 2; i <= NF; i++) print $i }'
                grep -hE '^deb ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null |
                    awk '{ for (i = 2; i <= NF; i++) if ($i ~ /:\/\//) { print $i; break } }'
            } | grep -v security | head -n 1 || true
        )}
        [ -n "$mirror" ] || die "no Debian mirror in the apt sources; set DEBIAN_MIRROR"
        mkdir -p "$cache"
        root=$(mktemp -d "$cache/rootfs.XXXXXX")
        trap 'rm -rf "$root"' EXIT
        echo "build-local: debootstrap $suite (minbase + ca-certificates) from $mirror"
        PATH="$PATH:/usr/sbin:/sbin" debootstrap --variant=minbase --include=ca-certificates \
            "$suite" "$root" "$mirror" >"$cache/debootstrap.log" 2>&1 ||
            die "debootstrap failed; see $cache/debootstrap.log"
        # What a container never uses: package caches and lists, documentation, manuals.
        rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/* \
            "$root"/usr/share/doc/* "$root"/usr/share/man/* "$root"/usr/share/info/*
        tar --numeric-owner -C "$root" -cf "$tarball.partial" .
        mv "$tarball.partial" "$tarball"
        rm -rf "$root"
        trap - EXIT
    fi
    echo "build-local: docker import $tarball as $base"
    docker import --change 'CMD ["/bin/bash"]' "$tarball" "$base" >/dev/null
fi

# ---- the binaries
if [ -n "${HAC_BINARIES:-}" ]; then
    bin=$HAC_BINARIES
else
    command -v cargo >/dev/null || die "cargo is not on PATH (or set HAC_BINARIES)"
    echo "build-local: cargo build --release"
    (cd "$repo" && cargo build --release --locked -p hac-cli -p hac-learner-service -p hac-actor-service)
    bin=$(cd "$repo" && cargo metadata --format-version 1 --no-deps |
        sed -E 's/.*"target_directory":"([^"]*)".*/\1/')/release
fi
for b in hac hac-learner hac-actor; do
    [ -x "$bin/$b" ] || die "$bin/$b is missing"
done

# ---- the runtime image: the base, the user and the binaries. A context of its own (three
# binaries and the Dockerfile), built by the classic builder, which uses the local base as it is
# (BuildKit would ask a registry about it).
context=$(mktemp -d)
trap 'rm -rf "$context"' EXIT
cp "$repo/deploy/docker/Dockerfile.local" "$context/Dockerfile"
cp "$bin/hac" "$bin/hac-learner" "$bin/hac-actor" "$context/"
# The release profile keeps debug info (for profiling); the image does without it.
if command -v strip >/dev/null; then
    strip --strip-debug "$context/hac" "$context/hac-learner" "$context/hac-actor"
fi
echo "build-local: docker build $image from $base"
DOCKER_BUILDKIT=0 docker build -q --build-arg "BASE=$base" -t "$image" "$context" >/dev/null 2>"$context/build.log" ||
    { cat "$context/build.log" >&2; die "docker build failed"; }
docker run --rm "$image" hac --version >/dev/null || die "$image does not run hac --version"
echo "build-local: built $image ($(docker image inspect -f '{{.Size}}' "$image" | awk '{ printf "%.0f MB", $1 / 1e6 }'))"
