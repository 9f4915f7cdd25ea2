"""Analysis beyond the pipeline: model-discrepancy diagnosis, identifiability, method comparison, evaluation."""
