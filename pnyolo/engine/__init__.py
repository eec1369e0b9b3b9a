"""The engine: ``predict`` (every model run outside training), ``ray_selection`` (which rays a step renders),
``checkpoint`` (atomic checkpoints, loading a detector), ``weight_average`` (EMA of the weights),
``logs`` (log.jsonl, epochs.csv)."""
