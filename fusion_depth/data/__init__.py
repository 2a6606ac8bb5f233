"""Datasets: one module per dataset, plus the shared datamodule and transforms."""
