"""The JSGS method (JPEG State-Guided Supervision) as a loss hook of the generic trainer.

- :mod:`jsgs.method.options`: ``method_options`` of ``--method jsgs`` (typed, with the speed settings apart);
- :mod:`jsgs.method.image_terms`: the JO -> L_obs -> DS chain of one view and the views' JPEG tables;
- :mod:`jsgs.method.pooling`: the probe that pools the block scores per Gaussian for the Gaussian Controller
  (whose math, L_fro and its closed-form gradient, is :func:`jsgs.kernels.fro_from_probe_grad`, beside its
  fused CUDA kernel);
- :mod:`jsgs.method.graphed`: the image terms and the controller replayed as CUDA graphs;
- :mod:`jsgs.method.hook`: :class:`~jsgs.method.hook.JsgsHook` and its factory, registered with the trainer
  as ``jsgs`` (:mod:`jsgs.train.method`).

Importing this package imports none of these modules; the trainer loads the hook when a run asks for it.
"""
