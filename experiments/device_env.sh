# Sourced at the start of a lent GPU machine's call (repository root): unpacks what the call
# carried -- the trimmed site archive (.whl/split/site.part.*, joined; or .whl/site.tar.xz, or the
# wheels .whl/*.whl installed) into
# /tmp/site and the Menagerie archive (.menagerie/menagerie_all.tar.xz) beside it -- once per
# machine, and exports what the jobs read. Returns non-zero (the call should stop) where either
# is missing.
#   source experiments/device_env.sh [COMMIT]   # COMMIT: this checkout's, for the results' code field
# (DEVICE_SITE: where the site goes, /tmp/site by default, where table1_device.sh looks;
# JAX_COMPILATION_CACHE_DIR: JAX's persistent compilation cache, /tmp/jax_cache by default.)
# The call then carries [".whl/split/site.part.aa", ".menagerie/menagerie_all.tar.xz"] (15.6 MB)
# beside a tree cut by `experiments/device_tree.sh out ...`; docs/reproduce.md.
_device_env() {
  local site=${DEVICE_SITE:-/tmp/site}
  if [ ! -f "$site/.done" ]; then
    mkdir -p "$site"
    if ls .whl/split/site.part.* >/dev/null 2>&1; then
      cat .whl/split/site.part.* | tar -C "$site" -xJ || return 3
    elif [ -f .whl/site.tar.xz ]; then
      tar -C "$site" -xJf .whl/site.tar.xz || return 3
    elif ls .whl/*.whl >/dev/null 2>&1; then  # the cp312 wheels themselves
      python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target "$site" .whl/*.whl || return 3
    else
      echo "device_env: no carried site (.whl/split/site.part.*, .whl/site.tar.xz or .whl/*.whl)" >&2
      return 3
    fi
    touch "$site/.done"
  fi
  if [ ! -d .menagerie/menagerie ]; then
    local mn="" f
    for f in .menagerie/menagerie_all.tar.xz .menagerie/menagerie.tar.xz; do
      [ -f "$f" ] && { mn=$f; break; }
    done
    [ -n "$mn" ] || { echo "device_env: no carried .menagerie/menagerie_all.tar.xz" >&2; return 3; }
    tar -C .menagerie -xJf "$mn" || return 3
  fi
  export PYTHONPATH=$site:$PWD MENAGERIE_ROOT=$PWD/.menagerie/menagerie PYTHONUNBUFFERED=1
  # JAX's persistent compilation cache on the machine: a later call on the same warm machine
  # (or a resumed part) reuses what an earlier one compiled (G1's closed loop: 25-45 s per
  # model kind and terrain, recompiled by every call before this); jobs that set their own keep it
  export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/jax_cache}
  export STRIDE_COMMIT=${1:-${STRIDE_COMMIT:-}}
}
_device_env "$@"
