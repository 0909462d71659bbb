"""The trainer: gsplat-recipe backbone, evaluation, checkpoints; methods plug in through hooks."""
