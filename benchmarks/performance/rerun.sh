#!/usr/bin/env bash
# The commands of docs/results/performance.md's sections "The daemon's CPU a cycle", "Rate at
# the computed bound", "16 chips at 100 Hz, burst, a Pi 4's adapter", "Latency from a sample
# to its subscribers" and "Control floods", in one run, with the host's load and the
# hypervisor's steal between them. Run on a quiet machine (about 6 min):
#   bash benchmarks/performance/rerun.sh > rerun.txt 2>&1
set -euo pipefail
cd "$(dirname "$0")/../.."
host() { uptime; head -1 /proc/stat | awk '{print "cpu ticks: steal", $9, "of", $2+$3+$4+$5+$6+$7+$8+$9}'; }
host
python -m benchmarks.performance.cycle_cpu
host
for a in permissive bcm2835 designware; do
  ftsensord doctor --bus "sim?adapter=$a&ioctl_us=80" --json --real-time
done
host
python -m benchmarks.performance.rate --seconds 30 --adapter bcm2835 --ioctl-us 80
python -m benchmarks.performance.rate --seconds 30 --adapter bcm2835 --ioctl-us 80 --fifo 50
python -m benchmarks.performance.rate --seconds 30 --adapter bcm2835 --ioctl-us 80 --fifo 50
host
python -m benchmarks.performance.latency --subscribers 50 --seconds 20
python -m benchmarks.performance.latency --subscribers 50 --seconds 20 --kind c
python -m benchmarks.performance.latency --subscribers 50 --seconds 20 --kind c --fifo 50
python -m benchmarks.performance.latency --subscribers 50 --seconds 20 --kind c --fifo 50 --shared-context
python -m benchmarks.performance.latency --subscribers 1 --processes 1 --seconds 20 --kind c --fifo 50
host
python -m benchmarks.robustness.flood status --seconds 20 --clients 4 --fifo 50
python -m benchmarks.robustness.flood status --seconds 20 --clients 4
host
