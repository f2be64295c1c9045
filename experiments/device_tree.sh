#!/usr/bin/env bash
# Leaves large committed folders out of the tree a device call sends (its working tree and the
# carried files are capped together at 64 MiB: /work/.library/device/README.md), and puts them
# back. A device call sends tracked files and untracked files git does not ignore, so a folder
# that is untracked and listed in .git/info/exclude stays here.
#   bash experiments/device_tree.sh out [PATH...]   # default PATH: results/models
#   bash experiments/device_tree.sh back            # the index and .git/info/exclude as before
#   bash experiments/device_tree.sh status          # what is out, and the tracked tree's size
#   bash experiments/device_tree.sh size            # the tracked tree's size in bytes, alone
# While folders are out, `git status` shows them deleted from the index: commit only with paths
# (`git commit -- PATH...`), or put them back first. `out` twice is refused (one set at a time).
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
git_dir=$(git rev-parse --git-dir)
state=$git_dir/device_tree_out
exclude=$git_dir/info/exclude
# (du -c over xargs prints one total per batch of names: sum the sizes instead)
tree_size() { git ls-files -z | xargs -0 stat -c %s 2>/dev/null | awk '{s += $1} END {print s + 0}'; }

case "${1:-}" in
  out)
    shift
    [ ! -s "$state" ] || { echo "already out: $(tr '\n' ' ' < "$state")(run 'back' first)" >&2; exit 1; }
    paths=("$@"); [ ${#paths[@]} -gt 0 ] || paths=(results/models)
    for p in "${paths[@]}"; do
      [ -n "$(git ls-files -- "$p" | head -1)" ] || { echo "$p: no tracked files" >&2; exit 1; }
    done
    mkdir -p "$(dirname "$exclude")"
    for p in "${paths[@]}"; do
      p=${p%/}
      git rm -r -q --cached -- "$p"
      echo "/$p/" >> "$exclude"
      echo "$p" >> "$state"
    done
    echo "out: ${paths[*]}; tracked tree now $(tree_size) bytes"
    ;;
  back)
    [ -s "$state" ] || { echo "nothing is out"; exit 0; }
    while read -r p; do
      git reset -q -- "$p"
      grep -vxF "/$p/" "$exclude" > "$exclude.tmp" || true
      mv "$exclude.tmp" "$exclude"
    done < "$state"
    rm -f "$state"
    echo "back; tracked tree $(tree_size) bytes"
    ;;
  size)
    tree_size
    ;;
  status)
    if [ -s "$state" ]; then echo "out: $(tr '\n' ' ' < "$state")"; else echo "nothing is out"; fi
    echo "tracked tree $(tree_size) bytes"
    ;;
  *)
    echo "usage: bash experiments/device_tree.sh out [PATH...] | back | status | size" >&2; exit 2
    ;;
esac
