"""python-can buses whose timeouts run on a simulated clock.

Role: the base of every bus that lives in simulated time (the scripted protocol bus, the
lockstep HIL's bus). python-can's :meth:`can.BusABC.recv` owns the receive policy (software
filters, retries) and measures its timeout on the wall clock: when ``_recv_internal`` returns
None before ``timeout`` seconds of ``time.time()`` have passed, it calls ``_recv_internal``
again. A bus whose empty wait moves a simulated clock instead of waiting would be asked to wait
again and again until that much wall time had passed. :class:`SimulatedTimeBus` keeps
python-can's policy and measures it on the bus's own clock instead.

Rules for a backend: implement ``send``, ``_recv_internal`` and :meth:`SimulatedTimeBus.now_s`
(and ``shutdown`` when there is something to release). ``_recv_internal(timeout)`` returns a
queued frame at once; with none it moves its clock by ``timeout`` (or by a bounded wait of its
own for ``timeout=None``) and returns what arrived meanwhile or None. A None ends the receive:
the backend has waited the whole timeout on its clock.
"""

from __future__ import annotations

import abc

import can

__all__ = ["SimulatedTimeBus"]


class SimulatedTimeBus(can.BusABC):
    """A ``can.BusABC`` whose receive timeout is measured on :meth:`now_s` (see the module
    docstring). Safe inside the loop: no allocation beyond what the backend's hooks make."""

    @abc.abstractmethod
    def now_s(self) -> float:
        """The bus's clock (s)."""

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame that passes the filters, or None when ``timeout`` seconds of the bus's
        clock passed without one (``None``: as long as the backend's bounded wait allows).

        Raises:
            can.CanOperationError: The backend failed (e.g. the bus is shut down).
        """
        start_s = self.now_s()
        time_left = timeout
        while True:
            msg, already_filtered = self._recv_internal(timeout=time_left)
            if msg is None:
                return None
            if already_filtered or self._matches_filters(msg):
                return msg
            if timeout is not None:
                time_left = timeout - (self.now_s() - start_s)
                if time_left <= 0.0:
                    return None
