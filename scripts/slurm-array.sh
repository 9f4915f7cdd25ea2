#!/usr/bin/env bash
# One dfxcorr reconstruction per task of a SLURM job array, over a list of scans (one path per line).
#
#   sbatch --array=1-$(wc -l < scans.txt) scripts/slurm-array.sh scans.txt results/ [site.yaml]
#
# Task N processes line N of the list (as `sed -n Np`); a finished result is skipped, so resubmitting the
# same array resumes it. A failed task exits non-zero and its reason is the last line of results/<stem>.log.
#
# Memory: a full-resolution clinical scan (195 x 2880 x 2880 uint16) peaks at the resident size measured by
# scripts/benchmark.py (docs/measurements.md); --mem leaves a margin above it. Binned 1440 x 1440 needs a quarter.
#SBATCH --job-name=dfxcorr
#SBATCH --cpus-per-task=2
#SBATCH --mem=3G
#SBATCH --time=00:15:00
#SBATCH --output=dfxcorr-%A_%a.out
set -euo pipefail
list=${1:?usage: sbatch --array=1-N slurm-array.sh SCAN_LIST OUTDIR [CONFIG]}
outdir=${2:?usage: sbatch --array=1-N slurm-array.sh SCAN_LIST OUTDIR [CONFIG]}
config=${3:-}
# HDF5's file locks fail or hang on some network file systems (NFS, Lustre without flock); each task reads
# its own scan and writes its own result, so the locks protect nothing here.
export HDF5_USE_FILE_LOCKING=FALSE
exec dfxcorr batch "$list" -o "$outdir" ${config:+-c "$config"} --array-index "${SLURM_ARRAY_TASK_ID:?not in a job array}"
