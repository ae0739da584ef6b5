#!/usr/bin/env bash
# Sizing a node: the served rate against the in-process rate (with the client free to use the
# other cores, then pinned onto the workers' two), and sample and render time against threads
# (1, 2, 4, 8, 16). Usage: bash tools/bench_node.sh [LOG]  (needs `cargo build --release`;
# prints the log's end; figures in docs/performance.md "How cost grows" and "The wire").
set -u
cd "$(dirname "$0")/.."
B=${MPIFLOW_BIN:-target/release/mpiflow}
L=${1:-${OUT:-/tmp}/bench_node.log}
{
nproc; lscpu | grep -E 'Model name|^CPU\(s\)|Thread|MHz'
echo "== serve, 2 workers, the other cores free"
for i in 1 2; do $B bench serve --workers 2 --count 96 --clients 0 2>&1 | tail -3; done
echo "== serve, 2 workers, pinned to 2 cores (taskset -c 0,1)"
for i in 1 2; do taskset -c 0,1 $B bench serve --workers 2 --count 96 --clients 0 2>&1 | tail -3; done
echo "== serve lz4, 2 workers"
$B bench serve --workers 2 --count 96 --clients 0 --lz4 2>&1 | tail -3
for t in 1 2 4 8 16; do echo "== sample threads $t"; $B bench sample --threads $t --samples 24 2>&1 | grep -E "^median|^  (render|objects|merge|inpaint) "; done
for t in 1 2 4 8 16; do echo "== render threads $t"; $B bench render --threads $t --runs 10 2>&1 | grep median; done
} > "$L" 2>&1
tail -c 11000 "$L"
