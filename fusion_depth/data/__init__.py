"""Datasets: one module per dataset, plus the shared datamodule and transforms."""

# The split names every dataset reader accepts (their order also keys the procedural seed streams).
SPLITS: tuple[str, ...] = ("train", "val", "test")
