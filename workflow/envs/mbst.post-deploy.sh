#!/usr/bin/env bash
# Run by Snakemake inside the new conda env, from the workflow's working
# directory (the repository root): install mbst itself, without touching the
# dependencies the env file pinned.
set -euo pipefail
python -m pip install --no-deps -e .
