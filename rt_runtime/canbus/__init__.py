"""CiA 301/402 master for the arm's cylinder drives over any python-can bus.

One module per protocol service (DESIGN.md "CAN protocol", STYLE.md after canopen):

=============  ==================================================================================
``cia402``     drive states, commands, targets; ``next_controlword(statusword, target, prev)``
               as a table (every transition 0-16, fault reset as a bit 7 edge)
``pdo``        COB-IDs, SYNC, precompiled PDO structs, ``check_pdo_mapping`` against the EDS
``nmt``        NMT commands/states and frames
``heartbeat``  heartbeat frames, producer and consumer driven by ``now_s``
``emcy``       EMCY decoding (codes as :class:`EmcyCode` where known) and frames
``sdo``        small SDO client (expedited download/upload, segmented upload) for configuration
``busload``    CAN 2.0A frame lengths (nominal, worst-case stuffed, exact) and bus load
``config``     what the master writes at boot: ``MasterConfig`` from the rig, the SDO
               downloads per drive, the EDS
``feedback``   the cycle's results: ``Feedback`` workspace, ``CycleStatus``, ``WriteStatus``
``router``     ``FrameRouter``: every frame the master reads, routed by COB-ID into ``Feedback``
``cyclic``     ``CyclicExchange``: frames out (stamped at send), setpoints and SYNC, the
               answers with the cycle's status and the fault reaction, heartbeat, stops
``master``     :class:`CanMaster`: boot and enable, and the cycle of ``cyclic``; uses all of
               the above
``scripted``   test equipment: ``ScriptedBus`` plays (TX, id, bytes) / (RX, id, bytes) exchanges
=============  ==================================================================================

Buses (python-can backends: ``send`` and ``_recv_internal``, nothing private of python-can):

=============  ==================================================================================
``simtime``    ``SimulatedTimeBus``: python-can's receive policy on a bus's own (simulated) clock
``inprocess``  ``InProcessChannel`` / ``ChannelBus``: one bus in one process, copy on send
``traced``     ``TracedBus``: any bus, every frame sent and received handed to a trace writer
=============  ==================================================================================

A bus may have ``send_many(msgs)`` (the messages in order, in one write): the master then sends
each cycle's RPDO1s and SYNC in one call (the 127.0.0.1 bridge's end has it); on any other bus
one ``send`` a frame.

The protocol modules read no clock: boot and enable take ``now_fn`` (monotonic or simulated
seconds), the cycle takes ``now_s``. Nothing here starts a thread: the master is the bus's only
reader, and hands every frame that is not its drives' to
``CanMaster(..., on_other_frame=callback)`` (the VCU client's status decoding, for one).

API for the executor and the HIL streamer
-----------------------------------------

Setup, outside the loop (raises :class:`~rt_runtime.errors.ExcavatorRtError` subclasses)::

    master = CanMaster(bus, rig, period_s=0.002)   # EDS checked against the codecs here
    master.boot(time.monotonic, timeout_s=1.0)     # NMT reset, SDO configuration, NMT start
    master.enable(time.monotonic, timeout_s=1.0)   # 402: shutdown -> switch on -> enable

``boot`` resets every drive, checks 0x1000/0x6502, reads 0x1008, writes the PDO mappings,
0x1006, 0x60C2, 0x6065/0x6066 (from ``rig.drives``), 0x607D (the rig's cylinder travel),
0x6085, 0x1017, 0x1016 and mode 8, starts the drives and waits for their OPERATIONAL heartbeats.
``enable`` holds every drive at its actual position while it steps the CiA 402 state machine
with RPDO2 (one step per SYNC period) and returns when every drive reports OPERATION_ENABLED;
it reads each drive's statusword by SDO first, since TPDO2 comes only when it changes.
It raises :class:`~rt_runtime.errors.DriveFault` if a drive stays in FAULT.

Each cycle (never raises for bus conditions, returns status codes)::

    fb = master.read_feedback(now_s, timeout_s=0.0)   # answers to the previous SYNC
    # fb.status: CycleStatus (OK, STALE, EMCY, NOT_ENABLED, HEARTBEAT_LOST, DRIVE_FAULT,
    #            BUS_ERROR); fb.position_um, fb.velocity_um_s (int32, shape (n,)), fb.state,
    #            fb.statusword, fb.stale, fb.emcys, fb.heartbeat_events, fb.reacted
    status = master.write_setpoints(stroke_um, velocity_um_s)   # RPDO1 x n, then SYNC
    master.heartbeat(now_s)                                       # sends when due

From ``boot`` on the drives watch the master's heartbeat (0x1016): whoever holds the master
calls ``heartbeat(now_s)`` at least once per heartbeat period, in the loop and between jobs
alike, or the drives take their heartbeat-loss fault reaction (EMCY 0x8130). While a drive is
OPERATION_ENABLED it also needs a SYNC and an RPDO1 within ``rig.drives.sync_timeout_s``
(EMCY 0x8250): keep calling ``write_setpoints`` (holding the position) while enabled.

Axis order is boom, stick, bucket, then swing on a rig with swing (``master.config.axes``,
:mod:`rt_runtime.axes`); setpoints are integer micrometres of stroke and micrometres per
second, the swing drive's microradians and microradians per second (the executor converts from
SI at this edge).
``read_feedback`` returns one reused :class:`Feedback` object; ``Feedback.copy()`` for other
threads. A TPDO is attributed to the latest SYNC sent (the SYNC has no counter byte), so a
TPDO that arrives only after the next SYNC counts for that one.

Safety: after ``enable``, when a drive sends an EMCY with a nonzero code, reports FAULT, loses
its heartbeat (or reboots), or leaves OPERATION_ENABLED, ``read_feedback`` sends quick stop
(0x0002) to every drive once (``react_to_faults=True``, the default) and reports it in
``Feedback.reacted``; the drives decelerate with 0x6085 and end in SWITCH_ON_DISABLED.
``quick_stop()`` does the same on demand; ``disable()`` sends disable voltage (power stages off
at once, for axes at rest); both are loop safe.
``bus_load(period_s)`` gives the cyclic traffic's load (the VCU's status too, on a rig with a VCU).
"""

from rt_runtime.canbus.busload import (
    BusLoad,
    bus_load,
    bus_load_report,
    cia402_cycle_frames,
    frame_bits_exact,
    frame_bits_nominal,
    frame_bits_worst,
    vcu_cycle_frames,
)
from rt_runtime.canbus.cia402 import (
    Command,
    DriveState,
    Target,
    decode_state,
    next_controlword,
)
from rt_runtime.canbus.config import DEFAULT_EDS, DriveInfo, MasterConfig
from rt_runtime.canbus.emcy import Emcy, EmcyCode, emcy_meaning, emcy_message, parse_emcy
from rt_runtime.canbus.feedback import CycleStatus, Feedback, RxCounts, WriteStatus
from rt_runtime.canbus.heartbeat import (
    HeartbeatConsumer,
    HeartbeatEvent,
    HeartbeatEventKind,
    HeartbeatProducer,
)
from rt_runtime.canbus.master import CanMaster
from rt_runtime.canbus.nmt import NmtCommand, NmtState
from rt_runtime.canbus.pdo import RPDO1, RPDO2, TPDO1, TPDO2, PdoSpec, check_pdo_mapping
from rt_runtime.canbus.sdo import SdoAbortedError, SdoClient, SdoProtocolError, SdoTimeoutError

__all__ = [
    "DEFAULT_EDS",
    "RPDO1",
    "RPDO2",
    "TPDO1",
    "TPDO2",
    "BusLoad",
    "CanMaster",
    "Command",
    "CycleStatus",
    "DriveInfo",
    "DriveState",
    "Emcy",
    "EmcyCode",
    "Feedback",
    "HeartbeatConsumer",
    "HeartbeatEvent",
    "HeartbeatEventKind",
    "HeartbeatProducer",
    "MasterConfig",
    "NmtCommand",
    "NmtState",
    "PdoSpec",
    "RxCounts",
    "SdoAbortedError",
    "SdoClient",
    "SdoProtocolError",
    "SdoTimeoutError",
    "Target",
    "WriteStatus",
    "bus_load",
    "bus_load_report",
    "check_pdo_mapping",
    "cia402_cycle_frames",
    "decode_state",
    "emcy_meaning",
    "emcy_message",
    "frame_bits_exact",
    "frame_bits_nominal",
    "frame_bits_worst",
    "next_controlword",
    "parse_emcy",
    "vcu_cycle_frames",
]
