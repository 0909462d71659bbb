"""The generic trainer: gsplat-recipe backbone (:mod:`jsgs.train.trainer`), callbacks, evaluation,
checkpoints; methods plug in through the loss-hook protocol (:mod:`jsgs.train.hook`) and the method registry
(:mod:`jsgs.train.method`)."""
