"""The harness: the one place that joins the runtime and the HIL.

What runs the runtime's master and loop against the emulated rig lives here, and only here:
the ``hil`` command (:mod:`hil_sim.harness.cli`), the ``demo`` command
(:mod:`hil_sim.harness.demo`), the real-time HIL process (:mod:`hil_sim.harness.realtime`) and
the ``bench hil`` benchmark (:mod:`hil_sim.harness.bench`). The runtime's CLI finds them
through entry points (``excavator_rt.commands``, ``excavator_rt.bench``, ``excavator_rt.hil``
in ``pyproject.toml``); ``rt_runtime`` never imports ``hil_sim``.
"""
