#!/usr/bin/env bash
# Puts a generated table into a document: replaces what lies between the lines
# `<!-- generated: FILE -->` and `<!-- /generated: FILE -->` of DOC with FILE's text.
# Tables are written by benchmarks (stamped with commit, machine and date) into
# docs/benchmarks/, never by hand; the test
# `e2e::docs::every_generated_block_is_the_file_it_names` fails when a block and its file
# disagree.
#
#   bash scripts/insert-generated.sh BENCHMARKS.md docs/benchmarks/memory.md
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -eq 2 ] || { echo "usage: $0 DOC FILE" >&2; exit 2; }
python3 - "$1" "$2" <<'PY'
import sys
doc, file = sys.argv[1:]
begin, end = f"<!-- generated: {file} -->", f"<!-- /generated: {file} -->"
text = open(doc).read()
if begin not in text or end not in text:
    sys.exit(f"{doc} has no {begin} ... {end} block")
head, rest = text.split(begin, 1)
_, tail = rest.split(end, 1)
table = open(file).read().strip("\n")
open(doc, "w").write(f"{head}{begin}\n{table}\n{end}{tail}")
print(f"{doc}: {file} inserted")
PY
