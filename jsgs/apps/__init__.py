"""The top layer of jsgs: what sits on a trained run, the trainer and the method, and which nothing below
imports.

- :mod:`jsgs.apps.viewer` (``jsgs view``: the browser viewer, also live beside a training run);
- :mod:`jsgs.apps.render_video` (``jsgs render``) and :mod:`jsgs.apps.camera_path`, the paths it follows;
- :mod:`jsgs.apps.opcount`: the kernels a piece of torch code launches (the method's step among them).
"""
