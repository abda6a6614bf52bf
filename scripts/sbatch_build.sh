#!/usr/bin/env bash
# A hoidata command (build-sdf, render-synthetic, export) as a Slurm job array: one part per array task; the
# last task to finish writes the index (docs/cluster.md). The command goes after the script, without --part
# and --workers (each task takes its part from SLURM_ARRAY_TASK_ID and uses its CPUs as workers):
#
#   sbatch scripts/sbatch_build.sh build-sdf --dataset dexycb_full --root /data/dexycb --out /shared/stores/dexycb
#   sbatch scripts/sbatch_build.sh render-synthetic --source /data/ho3d --count 100000 --out /shared/stores/synth
#   sbatch --array=5 scripts/sbatch_build.sh build-sdf ...   # part 5 of 32 again (HOIDATA_PARTS keeps the count)
#
# Change --array and HOIDATA_PARTS together; add #SBATCH --account / --partition lines as your cluster needs.
#SBATCH --job-name=hoidata-build
#SBATCH --array=0-31
#SBATCH --cpus-per-task=16
#SBATCH --mem-per-cpu=2G
#SBATCH --time=04:00:00
#SBATCH --output=slurm-%x-%A_%a.log
set -euo pipefail
export HOIDATA_PARTS=${HOIDATA_PARTS:-32}  # the number of parts: the size of --array above
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}  # offscreen mask rendering on nodes without a display
HOIDATA=${HOIDATA:-hoidata}  # the command to run (e.g. "python -m hoidata.cli" from a source tree)
if [ "$#" -eq 0 ]; then
  echo "usage: sbatch $0 build-sdf|render-synthetic|export OPTIONS... (see docs/cluster.md)" >&2
  exit 2
fi
echo "part ${SLURM_ARRAY_TASK_ID:-?} of $HOIDATA_PARTS on $(hostname): $HOIDATA $*"
# shellcheck disable=SC2086 # HOIDATA may be several words
exec $HOIDATA "$@" --workers "${SLURM_CPUS_PER_TASK:-1}"
