#!/usr/bin/env bash
# Puts the outside tools that the opt-in tests need (HAC_TEST_TOOLS=1) on PATH, installing them
# from Debian's packages where they are missing. Sourced by .ci/run; prints what it uses.
#
# kubectl: the deploy tests render deploy/k8s with `kubectl kustomize`, and the overlays use
# kustomize components, which need kustomize v5 (kubectl 1.27 or newer). Debian 12's
# kubernetes-client is 1.20, so the kubectl package of Debian 13 (trixie) is fetched from the
# machine's own Debian mirror and unpacked into a cache directory: the system's package set and
# apt sources are left as they are.

hac_kubectl_ok() {
    command -v kubectl >/dev/null 2>&1 &&
        kubectl version --client 2>/dev/null | grep -qE 'Kustomize Version: v([5-9]|[1-9][0-9])'
}

hac_debian_mirror() {
    # The first Debian archive URI the machine's apt sources name (not the security archive).
    {
        grep -hE '^URIs:' /etc/apt/sources.list.d/*.sources 2>/dev/null | awk '{ for (i = 2; i <= NF; i++) print $i }'
        grep -hE '^deb ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null |
            awk '{ for (i = 2; i <= NF; i++) if ($i ~ /:\/\//) { print $i; break } }'
    } | grep -v security | head -n 1
}

# Downloads the Debian 13 (trixie) package $1 from the machine's own Debian mirror and unpacks it
# into the cache directory $2 (its files under $2/root): the system's package set and apt sources
# are left as they are.
hac_unpack_trixie_package() {
    local package=$1 cache=$2
    local mirror
    mirror=$(hac_debian_mirror)
    if [ -z "$mirror" ]; then
        echo "tools: no Debian mirror in the apt sources; cannot fetch $package" >&2
        return 1
    fi
    echo "tools: unpacking $package from Debian 13's packages ($cache)"
    rm -rf "$cache" && mkdir -p "$cache/lists/partial" "$cache/debs"
    echo "deb $mirror trixie main" >"$cache/sources.list"
    : >"$cache/status"
    # Its own sources, lists and an empty package status, so that what the machine has installed
    # does not decide which version is downloaded.
    local apt=(-o "Dir::Etc::SourceList=$cache/sources.list" -o Dir::Etc::SourceParts=/dev/null
        -o "Dir::State::Lists=$cache/lists" -o "Dir::State::status=$cache/status"
        -o APT::Sandbox::User=root)
    apt-get "${apt[@]}" -qq update >/dev/null &&
        (cd "$cache/debs" && apt-get "${apt[@]}" -qq download "$package") &&
        dpkg -x "$cache"/debs/"$package"_*.deb "$cache/root"
}

hac_install_kubectl() {
    local cache="${XDG_CACHE_HOME:-$HOME/.cache}/hac-ci/kubectl"
    if [ -x "$cache/root/usr/bin/kubectl" ]; then
        export PATH="$cache/root/usr/bin:$PATH"
        hac_kubectl_ok && return 0
    fi
    hac_unpack_trixie_package kubectl "$cache" || return 1
    export PATH="$cache/root/usr/bin:$PATH"
    hac_kubectl_ok
}

hac_kubectl_ok || hac_install_kubectl || {
    echo "tools: kubectl with kustomize v5 is not available" >&2
    exit 1
}
echo "tools: $(command -v kubectl) ($(kubectl version --client 2>/dev/null | tr '\n' ' '))"

# docker: the cluster tests (services/hac/tests/containers.rs) run the Compose stack for real.
# They need the Docker engine, `docker compose` (Compose v2; Debian 12 has only the Python
# docker-compose 1.x, so the docker-compose package of Debian 13 is unpacked into the cache and
# linked as the user's CLI plugin, ~/.docker/cli-plugins) and debootstrap, which makes the image's
# base (deploy/docker/build-local.sh; installed from Debian's packages when missing).
hac_compose_ok() {
    docker compose version 2>/dev/null | grep -qE 'version v?2\.'
}

hac_install_compose() {
    local cache="${XDG_CACHE_HOME:-$HOME/.cache}/hac-ci/docker-compose"
    local plugin="$cache/root/usr/libexec/docker/cli-plugins/docker-compose"
    if [ ! -x "$plugin" ]; then
        hac_unpack_trixie_package docker-compose "$cache" || return 1
    fi
    local plugins="${DOCKER_CONFIG:-$HOME/.docker}/cli-plugins"
    mkdir -p "$plugins" && ln -sf "$plugin" "$plugins/docker-compose"
    hac_compose_ok
}

command -v docker >/dev/null 2>&1 && docker info >/dev/null 2>&1 || {
    echo "tools: the Docker engine is not reachable (docker info fails)" >&2
    exit 1
}
hac_compose_ok || hac_install_compose || {
    echo "tools: docker compose (v2) is not available" >&2
    exit 1
}
if ! command -v debootstrap >/dev/null 2>&1 && [ ! -x /usr/sbin/debootstrap ]; then
    echo "tools: installing debootstrap from Debian's packages"
    apt-get -qq update >/dev/null && apt-get install -y -qq debootstrap >/dev/null || {
        echo "tools: cannot install debootstrap" >&2
        exit 1
    }
fi
echo "tools: $(command -v docker) (engine $(docker version --format '{{.Server.Version}}')), $(docker compose version), $(command -v debootstrap || echo /usr/sbin/debootstrap)"
