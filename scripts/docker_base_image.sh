#!/usr/bin/env bash
# Make the image deploy/Dockerfile starts FROM (python:3.11-slim) when no registry can
# give it: a Debian bookworm root file system (Python 3.11) from debootstrap, imported
# under that tag. Safe to run again: it does nothing when the image exists or pulls.
#   bash scripts/docker_base_image.sh [TAG]
# Needs root (debootstrap) and a running Docker engine.
set -euo pipefail

TAG=${1:-python:3.11-slim}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}

if docker image inspect "$TAG" >/dev/null 2>&1; then
    echo "base image: $TAG is present"
    exit 0
fi
if timeout 60 docker pull "$TAG" >/dev/null 2>&1; then
    echo "base image: pulled $TAG"
    exit 0
fi
if ! command -v debootstrap >/dev/null; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq debootstrap
    else
        echo "base image: cannot pull $TAG and debootstrap is missing (apt-get install debootstrap)" >&2
        exit 1
    fi
fi

ROOT=$(mktemp -d)
trap 'rm -rf "$ROOT"' EXIT
echo "base image: no registry gives $TAG; building it with debootstrap (bookworm) in $ROOT"
# python-is-python3 gives `python`; python3-venv lets the Dockerfile make its virtualenv.
debootstrap --variant=minbase \
    --include=python3,python3-venv,python-is-python3,ca-certificates \
    bookworm "$ROOT" "$MIRROR" >/dev/null
rm -rf "$ROOT"/var/cache/apt/archives/*.deb "$ROOT"/var/lib/apt/lists/*
# The same environment the official image declares, so the Dockerfile builds unchanged.
tar -C "$ROOT" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["python3"]' \
    - "$TAG" >/dev/null
echo "base image: imported $TAG"
