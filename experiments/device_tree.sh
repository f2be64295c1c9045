#!/usr/bin/env bash
# Leaves large committed folders out of the tree a device call sends (its working tree and the
# carried files are capped together at 64 MiB: /work/.library/device/README.md), and puts them
# back. A device call sends tracked files and untracked files git does not ignore, so a folder
# that is untracked and listed in .git/info/exclude stays here.
#   bash experiments/device_tree.sh out [PATH...]   # default PATH: results/models
#   bash experiments/device_tree.sh back            # the index and .git/info/exclude as before
#   bash experiments/device_tree.sh status          # what is out, and the tracked tree's size
#   bash experiments/device_tree.sh size            # the tracked tree's size in bytes, alone
#   bash experiments/device_tree.sh keep [PATH...]  # out: every trained model and policy folder
#       (results/models/*, results/policies/*) and the large result folders (HEAVY below), but
#       the PATHs a call needs and the folders that hold them (a PATH inside a folder keeps that
#       folder's other entries out); e.g. keep results/policies/ppo_g1_soft_ent
# While folders are out, `git status` shows them deleted from the index: commit only with paths
# (`git commit -- PATH...`), or put them back first. `out` twice is refused (one set at a time).
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
git_dir=$(git rev-parse --git-dir)
state=$git_dir/device_tree_out
exclude=$git_dir/info/exclude
# (du -c over xargs prints one total per batch of names: sum the sizes instead)
tree_size() { git ls-files -z | xargs -0 stat -c %s 2>/dev/null | awk '{s += $1} END {print s + 0}'; }

# result folders too large to send that device calls have not needed
HEAVY=(results/closed_loop_g1_gpu results/closed_loop_go1_gpu results/closed_loop
       results/planning_diagnosis results/reproduce)

# the immediate entries (folders and files) git tracks under folder $1
children() { git ls-files -- "$1/" | sed "s|^$1/||" | cut -d/ -f1 | sort -u | sed "s|^|$1/|"; }

# what `keep` puts out of path $1 given the kept paths in $kept (one per line): nothing where $1
# is kept or lies in a kept path, its entries in turn where a kept path lies in it, else $1 (a
# folder)
leave_out() {
  local p=$1 k
  while IFS= read -r k; do
    [ -n "$k" ] || continue
    if [ "$p" = "$k" ] || [[ $p == "$k"/* ]]; then return; fi
  done <<< "$kept"
  while IFS= read -r k; do
    if [ -n "$k" ] && [[ $k == "$p"/* ]]; then
      local c
      for c in $(children "$p"); do leave_out "$c"; done
      return
    fi
  done <<< "$kept"
  [ ! -d "$p" ] || echo "$p"  # a file beside a kept one stays (the exclude file takes folders)
}

case "${1:-}" in
  keep)
    shift
    kept=""
    for k in "$@"; do
      k=${k%/}
      [ -n "$(git ls-files -- "$k" | head -1)" ] || { echo "$k: no tracked files" >&2; exit 1; }
      kept+="$k"$'\n'
    done
    paths=()
    for c in $(children results/models) $(children results/policies) "${HEAVY[@]}"; do
      [ -d "$c" ] && [ -n "$(git ls-files -- "$c" | head -1)" ] || continue
      while IFS= read -r p; do [ -n "$p" ] && paths+=("$p"); done < <(leave_out "$c")
    done
    [ ${#paths[@]} -gt 0 ] || { echo "keep: nothing to leave out"; exit 0; }
    exec bash "$0" out "${paths[@]}"
    ;;
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
    echo "usage: bash experiments/device_tree.sh out [PATH...] | keep [PATH...] | back | status | size" >&2; exit 2
    ;;
esac
