#!/usr/bin/env bash
# Set up a machine for COSMOS 3D Search, idempotently: Debian's libLLVM 19 for Mitsuba's fast JIT
# variant (when this user may install packages), a virtual environment in .venv, and the project
# with its dev extras. Re-running only reinstalls when pyproject.toml changed.
set -euo pipefail
cd "$(dirname "$0")/.."

have_libllvm() {
  compgen -G "/usr/lib/*/libLLVM.so.1[6-9]*" >/dev/null || compgen -G "/usr/lib/*/libLLVM-1[6-9].so" >/dev/null \
    || compgen -G "/usr/lib/*/libLLVM.so.2[0-9]*" >/dev/null || compgen -G "/usr/lib/*/libLLVM-2[0-9].so" >/dev/null
}

if ! have_libllvm; then
  if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null; then
    echo "bootstrap: installing libllvm19 for Mitsuba's llvm_ad_rgb variant"
    if ! (apt-get install -y -qq libllvm19 >/dev/null 2>&1 \
          || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq libllvm19 >/dev/null 2>&1; }); then
      echo "bootstrap: could not install libllvm19; the renderer will use scalar_rgb" >&2
    fi
  else
    echo "bootstrap: no libLLVM >= 16 and no way to install it; the renderer will use scalar_rgb" >&2
  fi
fi

# apt_package PACKAGE PRESENT WHAT: install Debian's PACKAGE unless the test PRESENT succeeds,
# when this user may (root, apt-get; one apt-get update if the first try fails); else say that
# WHAT cannot run. Those tests skip without it, except on CI, where they fail.
apt_package() {
  local package=$1 present=$2 what=$3
  if eval "$present"; then
    return
  fi
  if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null; then
    echo "bootstrap: installing $package for $what"
    if ! (DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$package" >/dev/null 2>&1 \
          || { apt-get update -qq >/dev/null 2>&1 \
               && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$package" >/dev/null 2>&1; }); then
      echo "bootstrap: could not install $package; $what cannot run" >&2
    fi
  else
    echo "bootstrap: no $package and no way to install it; $what will skip" >&2
  fi
}

# Debian's Chromium for the page's browser tests (Playwright drives /usr/bin/chromium; no
# browser is downloaded).
apt_package chromium "[[ -x /usr/bin/chromium ]]" "the browser tests (tests/web)"
# Debian's PostgreSQL for the store's tests on both back ends (tests/postgres_server.py starts a
# cluster of its own per test session; the package's own cluster is not used).
apt_package postgresql 'compgen -G "/usr/lib/postgresql/*/bin/initdb" >/dev/null' \
  "the PostgreSQL store tests (tests/controller)"

# Debian's iproute2 (`ip`, `tc`) for the hosts tests (tests/hosts: network namespaces, veth pairs,
# a bridge). Without it, or without root, those tests skip, except on CI, where they fail.
if ! command -v ip >/dev/null && [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null; then
  echo "bootstrap: installing iproute2 for the hosts tests"
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq iproute2 >/dev/null 2>&1 \
    || { apt-get update -qq >/dev/null 2>&1 \
         && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq iproute2 >/dev/null 2>&1; } \
    || echo "bootstrap: could not install iproute2; the hosts tests (tests/hosts) cannot run" >&2
fi

PYTHON=${PYTHON:-python3}
if [[ ! -x .venv/bin/python ]]; then
  "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
    || { echo "bootstrap: Python >= 3.11 is required ($PYTHON is $("$PYTHON" --version))" >&2; exit 1; }
  echo "bootstrap: creating .venv"
  "$PYTHON" -m venv .venv
fi

# The training extra (PyTorch) only when asked for, or when the CPU wheel lies on this disk: from
# PyPI a plain torch requirement pulls a multi-GB CUDA build.
extras=dev
case ${COSMOS_TRAINING:-auto} in
  1|yes|true) extras=dev,train ;;
  auto) compgen -G "${PIP_FIND_LINKS:-/opt/wheels}/torch-2.13.0+cpu-*.whl" >/dev/null && extras=dev,train ;;
esac

stamp=.venv/.cosmos-installed
want="$(sha256sum pyproject.toml | cut -d' ' -f1) $extras"
if [[ ! -f $stamp || $(cat "$stamp") != "$want" ]]; then
  echo "bootstrap: installing the project [$extras] into .venv (a few minutes the first time)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[$extras]"
  echo "$want" > "$stamp"
fi
