"""Running experiments: the LightningModule, its callbacks and loggers, checkpoints written and
rebuilt, run folders and their records, resume, sweeps and searches, the evaluation protocol,
speed settings and data-parallel ranks."""
