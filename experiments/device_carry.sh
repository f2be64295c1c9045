#!/usr/bin/env bash
# Splits what a lent GPU machine lacks (the cp312 wheels unpacked in .whl/site, and the Menagerie
# archive .menagerie/menagerie_all.tar.xz) into parts that fit beside the tracked tree in one
# device call (the call's working tree is capped; measured in session 27: 59.68 MB of tracked
# files plus a 4.30 MB part went, plus a 6.29 MB part was refused, so the cap is taken as
# 64,000,000 bytes of the files' sizes). Prints the calls, one after the other (the machine goes
# back after 30 s idle).
#   bash experiments/device_carry.sh            # -> .whl/split/{site,mn}.part.*
# The site archive leaves out what no job imports: MJX's test data (16 MB), MuJoCo's docs, PyOpenGL's
# Windows DLLs, caches and *_test.py files (13.2 -> 7.2 MB compressed).
set -eu
cd "$(git rev-parse --show-toplevel)"
[ -d .whl/site ] || { echo "no .whl/site: bash experiments/device_wheels.sh first"; exit 1; }
[ -f .menagerie/menagerie_all.tar.xz ] || { echo "no .menagerie/menagerie_all.tar.xz: bash experiments/device_wheels.sh first"; exit 1; }
cap=${CAP:-64000000}
tracked=$(bash experiments/device_tree.sh size)
part=$(( cap - tracked - 300000 ))
if [ "$part" -lt 1000000 ]; then
  echo "the tracked tree ($tracked bytes) leaves $part bytes per call under the cap $cap:" \
       "move large results out of git first"; exit 1
fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
cp -r .whl/site "$tmp/site"
rm -rf "$tmp/site/mujoco/mjx/test_data" "$tmp/site/mujoco/doc" "$tmp/site/OpenGL/DLLS"
find "$tmp/site" -name __pycache__ -prune -exec rm -rf {} +
find "$tmp/site" -name "*_test.py" -delete
tar -C "$tmp/site" -cJf .whl/site_trim.tar.xz .
rm -rf .whl/split && mkdir -p .whl/split
(cd .whl/split && split -b "$part" ../site_trim.tar.xz site.part. &&
 split -b "$part" ../../.menagerie/menagerie_all.tar.xz mn.part.)
echo "tracked tree $tracked bytes; parts of at most $part bytes:"
ls -l .whl/split | tail -n +2
echo "one call per part, carry .whl/split/<part>: mkdir -p /tmp/parts && cp .whl/split/<part> /tmp/parts/;"
echo "with the last site part: mkdir -p /tmp/site && cat /tmp/parts/site.part.* | tar -C /tmp/site -xJ && touch /tmp/site/.done"
echo "with the last mn part:   mkdir -p /tmp/mn && cat /tmp/parts/mn.part.* | tar -C /tmp/mn -xJ"
echo "then: export PYTHONPATH=/tmp/site:\$PWD MENAGERIE_ROOT=/tmp/mn/menagerie STRIDE_COMMIT=\$(git rev-parse --short HEAD here)"
