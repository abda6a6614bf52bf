#!/usr/bin/env bash
# Multi-node HOISDF training: one torchrun per node (srun), the rendezvous taken from the Slurm allocation
# (the first node of SLURM_JOB_NODELIST, the job id as the rendezvous id). Arguments go to hoisdf.train:
#
#   sbatch scripts/sbatch_train.sh --shards /shared/stores/dexycb --mano /data/mano --config dexycb \
#       --out /shared/runs/dexycb train.workers=8
#   sbatch scripts/sbatch_train.sh --shards https://store.lab/dexycb --mano /data/mano --out /shared/runs/x --resume
#
# --out must be on a filesystem every node sees (checkpoints); stores may be folders there or URLs.
#SBATCH --job-name=hoisdf-train
#SBATCH --nodes=2
#SBATCH --ntasks-per-node=1
#SBATCH --gpus-per-node=8
#SBATCH --cpus-per-task=64
#SBATCH --time=2-00:00:00
#SBATCH --output=slurm-%x-%j.log
set -euo pipefail
GPUS_PER_NODE=${GPUS_PER_NODE:-8}  # processes per node: one per GPU
RDZV_PORT=${RDZV_PORT:-29500}
head_node=$(scontrol show hostnames "$SLURM_JOB_NODELIST" | head -n 1)
echo "training on $SLURM_NNODES nodes x $GPUS_PER_NODE GPUs, rendezvous $head_node:$RDZV_PORT (id $SLURM_JOB_ID)"
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
srun --kill-on-bad-exit=1 torchrun --nnodes "$SLURM_NNODES" --nproc_per_node "$GPUS_PER_NODE" \
  --rdzv_id "$SLURM_JOB_ID" --rdzv_backend c10d --rdzv_endpoint "$head_node:$RDZV_PORT" \
  -m hoisdf.train "$@"
