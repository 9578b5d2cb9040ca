#!/usr/bin/env bash
# Make sure the system libraries for headless OpenGL (EGL + Mesa llvmpipe) are present, and
# Xvfb for the interactive viewer's window test.
# Installs them with apt-get when run as root on Debian/Ubuntu; otherwise says what to do.
# With CI=true (set by .ci/run) a machine where no headless EGL context can be created is an
# error (exit 1): CI always has GL, so GL tests must run there, not skip.
# PY names the Python that has moderngl (default: .venv/bin/python, else python3).
set -euo pipefail
PY=${PY:-.venv/bin/python}
[ -x "$PY" ] || PY=python3
in_ci() { [ "${CI:-}" = "true" ] || [ "${CI:-}" = "1" ]; }
egl_probe() {
  "$PY" - <<'PYCODE'
import sys
try:
    import moderngl
    ctx = moderngl.create_standalone_context(require=450, backend="egl")
    print(f"terrastream: headless OpenGL OK ({ctx.info['GL_RENDERER']}, {ctx.info['GL_VERSION']})")
    ctx.release()
except Exception as exc:  # any failure: no GL here
    sys.exit(f"terrastream: CI=true but no headless EGL / OpenGL 4.5 context can be created: {exc}")
PYCODE
}
finish() {  # $1: exit status when not in CI
  if in_ci; then
    egl_probe || exit 1
    exit 0
  fi
  exit "$1"
}
pkgs=(libegl1 libgl1-mesa-dri libgl1 libglx-mesa0 xvfb xauth libxrandr2 libxcursor1 libxi6 libxinerama1)
have() { ldconfig -p 2>/dev/null | grep -q "$1"; }
dri_ok() {
  for f in /usr/lib/*/dri/swrast_dri.so /usr/lib/dri/swrast_dri.so /usr/lib/*/dri/libdril_dri.so; do
    [ -e "$f" ] && return 0
  done
  return 1
}
if have libEGL.so.1 && have libGL.so.1 && dri_ok && command -v Xvfb >/dev/null; then
  finish 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing headless OpenGL libraries: ${pkgs[*]}"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${pkgs[@]}" >/dev/null
  finish 0
fi
cat >&2 <<MSG
terrastream: the headless OpenGL libraries (EGL + Mesa) are missing and this is not a root
Debian/Ubuntu shell, so they were not installed. Ask an administrator to run:
    apt-get update && apt-get install -y --no-install-recommends ${pkgs[*]}
Tiling and streaming work without them; rendering and the GL tests need them (GL tests skip),
and the viewer's window test needs Xvfb (it skips).
MSG
finish 0
