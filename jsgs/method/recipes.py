"""The ``method_options`` each preset gives ``--method jsgs`` (:data:`jsgs.train.config.PRESETS`; reached
through the method registry, :func:`jsgs.train.method.method_recipe`). A config file's ``method_options``
and the switches apply over them; a run's ``config.json`` records the result in full."""

from __future__ import annotations

from typing import Any

#: Preset name -> the JSGS options it sets. ``mcmc`` (the default preset) gives JSGS the recipe measured at
#: equal budget (docs/results/budget/default): λ_obs = 1 and λ_base per JPEG view,
#: w = 1 / (1 + (σ² / σ_ref²)²) with σ² estimated from the file's coefficients and σ_ref = 2; and the Gaussian
#: Controller on every 4th step (``gc_every`` 4, weighted 4·λ_fro there: at equal budget on flower, 3 seeds,
#: within the exact controller's seed spread, and 1.24 instead of 1.32 times gsplat's step at 1440×1920;
#: docs/results/speed/gc_quality). ``paper`` gives none: the paper's weights and its controller on every step
#: (the options' own defaults, :class:`jsgs.method.options.JsgsOptions`).
RECIPES: dict[str, dict[str, Any]] = {
    "mcmc": {
        "lambda_obs": 1.0,
        "base_by_view": True,
        "base_noise": "pixels",
        "base_noise_ref": 2.0,
        "base_noise_exponent": 2.0,
        "gc_every": 4,
    },
}
