"""Training-side code: dataset generation, physics-informed PINN training, ONNX export.

This subpackage needs the ``train`` extra (``pip install excavator-rt[train]``: torch 2.13.0,
matplotlib, tqdm). It is the only place that imports torch; the runtime (planning, control,
service) never imports it, so the rig PC runs without torch. Import its modules explicitly
(``from rt_runtime.training import physics``): this package file imports nothing itself.
"""
