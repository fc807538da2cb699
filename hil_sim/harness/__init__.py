"""The harness: the commands and the process that join the runtime and the HIL.

The ``hil`` command (:mod:`hil_sim.harness.cli`), the ``demo`` command
(:mod:`hil_sim.harness.demo`), the ``bench hil`` benchmark (:mod:`hil_sim.harness.bench`) and the
real-time HIL process (:mod:`hil_sim.harness.realtime`) with its 127.0.0.1 websocket bridge
(:mod:`hil_sim.harness.bridge`). The commands run the scenarios of
:mod:`hil_sim.harness.scenario` on the lockstep transport (:mod:`hil_sim.harness.lockstep`) and
report with :class:`hil_sim.harness.reports.HilReport`. The
runtime's CLI finds them through entry points (``excavator_rt.commands``,
``excavator_rt.bench``, ``excavator_rt.hil`` in ``pyproject.toml``); ``rt_runtime`` never
imports ``hil_sim``.
"""
