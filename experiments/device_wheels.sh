#!/usr/bin/env bash
# What a fresh checkout needs before `experiments/device_carry.sh`: the cp312 wheels a lent GPU
# machine lacks (its image has jax, flax, optax, orbax, chex but not MuJoCo, MJX, Brax or
# Menagerie; /work/.library/device/KINDS.md), at the versions this checkout's venv runs, unpacked
# into .whl/site; and the Menagerie archive .menagerie/menagerie_all.tar.xz from $MENAGERIE_ROOT.
#   bash experiments/device_wheels.sh        # then: bash experiments/device_carry.sh
# Needs the venv (`make setup`), unzip, and pip reaching a package index. Session 60: 26 s, 22 MB
# of wheels, site part 7.2 MB after device_carry.sh's trim, Menagerie archive 8.4 MB.
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
py=${PYTHON:-.venv/bin/python}
[ -x "$py" ] || { echo "device_wheels: no $py (make setup first)" >&2; exit 1; }
# the packages to carry (what our jobs import beyond the image, and what those import)
pkgs=(mujoco mujoco-core mujoco-mjx brax jaxopt ml_collections tensorboardX trimesh glfw
      PyOpenGL mujoco-menagerie)
pins=()
for p in "${pkgs[@]}"; do
  v=$("$py" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$p") || {
    echo "device_wheels: $p is not installed in $py's environment" >&2; exit 1; }
  pins+=("$p==$v")
done
plat=()
for t in manylinux_2_17 manylinux_2_24 manylinux_2_27 manylinux_2_28 manylinux_2_31 \
         manylinux_2_34 manylinux_2_35 manylinux2014 manylinux1; do
  plat+=(--platform "${t}_x86_64")
done
rm -rf .whl/dl && mkdir -p .whl/dl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
  --implementation cp "${plat[@]}" -d .whl/dl "${pins[@]}"
rm -rf .whl/site && mkdir -p .whl/site
for w in .whl/dl/*.whl; do  # unzip keeps the wheels' file modes (what session 60's GPU calls ran)
  unzip -q -o "$w" -d .whl/site
done
echo "device_wheels: ${#pins[@]} wheels (${pins[*]}) -> .whl/site"
root=${MENAGERIE_ROOT:-../shared/menagerie}
[ -d "$root" ] || { echo "device_wheels: no Menagerie at $root (set MENAGERIE_ROOT)" >&2; exit 1; }
mkdir -p .menagerie
root=$(cd "$root" && pwd)
# one top folder named menagerie, whatever the root's name (experiments/device_env.sh unpacks it so)
tar -C "$(dirname "$root")" --transform "s,^$(basename "$root"),menagerie," \
  -cJf .menagerie/menagerie_all.tar.xz "$(basename "$root")"
echo "device_wheels: $(du -h .menagerie/menagerie_all.tar.xz | cut -f1) .menagerie/menagerie_all.tar.xz"
