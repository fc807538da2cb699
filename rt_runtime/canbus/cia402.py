"""CiA 402 drive state machine as data: statusword decoding and the controlword to send next.

Role: the master's side of the CiA 402 (IEC 61800-7-201) power drive state machine. Pure tables
and functions, no I/O, no clock; safe inside the loop (no allocation beyond small ints).

States are decoded from the statusword with the standard masks (bits 0-3, 5, 6)::

    NOT_READY_TO_SWITCH_ON   xxxx xxxx x0xx 0000   mask 0x004F value 0x0000
    SWITCH_ON_DISABLED       xxxx xxxx x1xx 0000   mask 0x004F value 0x0040
    READY_TO_SWITCH_ON       xxxx xxxx x01x 0001   mask 0x006F value 0x0021
    SWITCHED_ON              xxxx xxxx x01x 0011   mask 0x006F value 0x0023
    OPERATION_ENABLED        xxxx xxxx x01x 0111   mask 0x006F value 0x0027
    QUICK_STOP_ACTIVE        xxxx xxxx x00x 0111   mask 0x006F value 0x0007
    FAULT_REACTION_ACTIVE    xxxx xxxx x0xx 1111   mask 0x004F value 0x000F
    FAULT                    xxxx xxxx x0xx 1000   mask 0x004F value 0x0008

Commands are the controlword patterns of bits 7, 3, 2, 1, 0 (the mode-specific bits 4-6 and halt,
bit 8, are sent as 0). CiA 402 gives *switch on* and *disable operation* the same bits
(0b0111); what the pattern does depends on the state it reaches, so ``Command.DISABLE_OPERATION``
is an alias of ``Command.SWITCH_ON``.

The transitions of CiA 402 Fig. "state machine" (numbers as in the standard)::

     0  start                  -> NOT_READY_TO_SWITCH_ON   automatic
     1  NOT_READY_TO_SWITCH_ON -> SWITCH_ON_DISABLED       automatic
     2  SWITCH_ON_DISABLED     -> READY_TO_SWITCH_ON       shutdown
     3  READY_TO_SWITCH_ON     -> SWITCHED_ON              switch on
     4  SWITCHED_ON            -> OPERATION_ENABLED        enable operation
     5  OPERATION_ENABLED      -> SWITCHED_ON              disable operation
     6  SWITCHED_ON            -> READY_TO_SWITCH_ON       shutdown
     7  READY_TO_SWITCH_ON     -> SWITCH_ON_DISABLED       disable voltage or quick stop
     8  OPERATION_ENABLED      -> READY_TO_SWITCH_ON       shutdown
     9  OPERATION_ENABLED      -> SWITCH_ON_DISABLED       disable voltage
    10  SWITCHED_ON            -> SWITCH_ON_DISABLED       disable voltage or quick stop
    11  OPERATION_ENABLED      -> QUICK_STOP_ACTIVE        quick stop
    12  QUICK_STOP_ACTIVE      -> SWITCH_ON_DISABLED       automatic after the quick-stop
                                                           reaction (0x605A 1-4), or disable voltage
    13  any (power on)         -> FAULT_REACTION_ACTIVE    a fault in the drive
    14  FAULT_REACTION_ACTIVE  -> FAULT                    automatic
    15  FAULT                  -> SWITCH_ON_DISABLED       fault reset (0 -> 1 edge of bit 7)
    16  QUICK_STOP_ACTIVE      -> OPERATION_ENABLED        enable operation (0x605A 5-8 only)

:data:`NEXT_COMMAND` maps (state, target) to the next command on the path; :func:`next_controlword`
adds the fault-reset edge. Fault reset needs a rising edge of bit 7, so the function takes the
previous controlword the master sent to that drive: if bit 7 was already high, it returns the
controlword with bit 7 low (0x0000, which also keeps a drive in FAULT), and the call after that
returns 0x0080 again. A master that calls it once per cycle therefore sends 0x0080, 0x0000,
0x0080, ... for as long as the drive stays in FAULT: one reset attempt every second cycle.
Choosing this over a two-step sequence keeps the function one lookup with one int of memory that
the caller already has (the last controlword it sent).

Design choices where the standard leaves a choice to the master:

* The way down from OPERATION_ENABLED to SWITCH_ON_DISABLED is 5 then 10 (disable operation,
  then disable voltage), never 9: disable operation lets the drive stop with its disable-operation
  reaction, while 9 removes power at speed.
* ``Target.QUICK_STOP`` is the safety target: it never resets a fault (FAULT stays FAULT, bit 7
  low), and outside OPERATION_ENABLED it sends the quick-stop pattern, which CiA 402 maps to
  SWITCH_ON_DISABLED (7, 10), the state where no axis is powered. The drive leaves
  QUICK_STOP_ACTIVE by itself (12) with quick stop option code 2 (the EDS default).
* ``Target.DISABLED``, ``SWITCHED_ON`` and ``OPERATION_ENABLED`` reset a fault (15), because the
  only path from FAULT to them runs through it. Whether to ask for them while a drive is in FAULT
  is the master's decision, not the table's.
* From QUICK_STOP_ACTIVE every target but QUICK_STOP goes down with disable voltage (12) and up
  again from SWITCH_ON_DISABLED; transition 16 is not used because it depends on an option code.
* NOT_READY_TO_SWITCH_ON and FAULT_REACTION_ACTIVE leave by themselves (1, 14); the table sends
  disable voltage (0x0000) there, which is harmless in both and primes the fault-reset edge.
* A statusword that decodes to no state (:func:`decode_state` returns None) gets the quick-stop
  pattern for every target: a drive whose state cannot be told must not be moved.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = [
    "CONTROLWORD_MASKS",
    "NEXT_COMMAND",
    "STATUSWORD_MASKS",
    "TRANSITIONS",
    "Command",
    "DriveState",
    "Target",
    "apply_controlword",
    "decode_command",
    "decode_state",
    "next_controlword",
]

FAULT_RESET_BIT = 0x0080


class DriveState(IntEnum):
    """States of the CiA 402 power drive state machine."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


class Command(IntEnum):
    """Device control commands; the value is the controlword pattern (bits 7, 3, 2, 1, 0).

    ``DISABLE_OPERATION`` has the same bits as ``SWITCH_ON`` (CiA 402) and is an alias of it.
    ``FAULT_RESET`` acts on the 0 -> 1 edge of bit 7 only.
    """

    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    ENABLE_OPERATION = 0x000F
    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    DISABLE_OPERATION = 0x0007
    FAULT_RESET = 0x0080


class Target(IntEnum):
    """Where the master wants a drive to go."""

    DISABLED = 0
    SWITCHED_ON = 1
    OPERATION_ENABLED = 2
    QUICK_STOP = 3


#: (mask, value) of the statusword per state, CiA 402 Table "state coding".
STATUSWORD_MASKS: dict[DriveState, tuple[int, int]] = {
    DriveState.NOT_READY_TO_SWITCH_ON: (0x004F, 0x0000),
    DriveState.SWITCH_ON_DISABLED: (0x004F, 0x0040),
    DriveState.READY_TO_SWITCH_ON: (0x006F, 0x0021),
    DriveState.SWITCHED_ON: (0x006F, 0x0023),
    DriveState.OPERATION_ENABLED: (0x006F, 0x0027),
    DriveState.QUICK_STOP_ACTIVE: (0x006F, 0x0007),
    DriveState.FAULT_REACTION_ACTIVE: (0x004F, 0x000F),
    DriveState.FAULT: (0x004F, 0x0008),
}

#: (mask, value) of the controlword per command, CiA 402 Table "device control commands", in
#: the order a drive tests them. SWITCH_ON and ENABLE_OPERATION require bit 7 low; fault reset
#: is an edge and is not in this table.
CONTROLWORD_MASKS: tuple[tuple[Command, int, int], ...] = (
    (Command.SHUTDOWN, 0x0087, 0x0006),
    (Command.SWITCH_ON, 0x008F, 0x0007),
    (Command.ENABLE_OPERATION, 0x008F, 0x000F),
    (Command.DISABLE_VOLTAGE, 0x0082, 0x0000),
    (Command.QUICK_STOP, 0x0086, 0x0002),
)

_S = DriveState
_T = Target
_C = Command

#: Next command on the path from a state to a target (see the module docstring for the choices).
#: FAULT_RESET entries are turned into the 0 -> 1 edge by :func:`next_controlword`.
NEXT_COMMAND: dict[tuple[DriveState, Target], Command] = {
    (_S.NOT_READY_TO_SWITCH_ON, _T.DISABLED): _C.DISABLE_VOLTAGE,
    (_S.NOT_READY_TO_SWITCH_ON, _T.SWITCHED_ON): _C.DISABLE_VOLTAGE,
    (_S.NOT_READY_TO_SWITCH_ON, _T.OPERATION_ENABLED): _C.DISABLE_VOLTAGE,
    (_S.NOT_READY_TO_SWITCH_ON, _T.QUICK_STOP): _C.DISABLE_VOLTAGE,
    (_S.SWITCH_ON_DISABLED, _T.DISABLED): _C.DISABLE_VOLTAGE,
    (_S.SWITCH_ON_DISABLED, _T.SWITCHED_ON): _C.SHUTDOWN,  # 2
    (_S.SWITCH_ON_DISABLED, _T.OPERATION_ENABLED): _C.SHUTDOWN,  # 2
    (_S.SWITCH_ON_DISABLED, _T.QUICK_STOP): _C.QUICK_STOP,
    (_S.READY_TO_SWITCH_ON, _T.DISABLED): _C.DISABLE_VOLTAGE,  # 7
    (_S.READY_TO_SWITCH_ON, _T.SWITCHED_ON): _C.SWITCH_ON,  # 3
    (_S.READY_TO_SWITCH_ON, _T.OPERATION_ENABLED): _C.SWITCH_ON,  # 3
    (_S.READY_TO_SWITCH_ON, _T.QUICK_STOP): _C.QUICK_STOP,  # 7
    (_S.SWITCHED_ON, _T.DISABLED): _C.DISABLE_VOLTAGE,  # 10
    (_S.SWITCHED_ON, _T.SWITCHED_ON): _C.SWITCH_ON,
    (_S.SWITCHED_ON, _T.OPERATION_ENABLED): _C.ENABLE_OPERATION,  # 4
    (_S.SWITCHED_ON, _T.QUICK_STOP): _C.QUICK_STOP,  # 10
    (_S.OPERATION_ENABLED, _T.DISABLED): _C.DISABLE_OPERATION,  # 5, then 10
    (_S.OPERATION_ENABLED, _T.SWITCHED_ON): _C.DISABLE_OPERATION,  # 5
    (_S.OPERATION_ENABLED, _T.OPERATION_ENABLED): _C.ENABLE_OPERATION,
    (_S.OPERATION_ENABLED, _T.QUICK_STOP): _C.QUICK_STOP,  # 11
    (_S.QUICK_STOP_ACTIVE, _T.DISABLED): _C.DISABLE_VOLTAGE,  # 12
    (_S.QUICK_STOP_ACTIVE, _T.SWITCHED_ON): _C.DISABLE_VOLTAGE,  # 12
    (_S.QUICK_STOP_ACTIVE, _T.OPERATION_ENABLED): _C.DISABLE_VOLTAGE,  # 12
    (_S.QUICK_STOP_ACTIVE, _T.QUICK_STOP): _C.QUICK_STOP,
    (_S.FAULT_REACTION_ACTIVE, _T.DISABLED): _C.DISABLE_VOLTAGE,
    (_S.FAULT_REACTION_ACTIVE, _T.SWITCHED_ON): _C.DISABLE_VOLTAGE,
    (_S.FAULT_REACTION_ACTIVE, _T.OPERATION_ENABLED): _C.DISABLE_VOLTAGE,
    (_S.FAULT_REACTION_ACTIVE, _T.QUICK_STOP): _C.DISABLE_VOLTAGE,
    (_S.FAULT, _T.DISABLED): _C.FAULT_RESET,  # 15
    (_S.FAULT, _T.SWITCHED_ON): _C.FAULT_RESET,  # 15
    (_S.FAULT, _T.OPERATION_ENABLED): _C.FAULT_RESET,  # 15
    (_S.FAULT, _T.QUICK_STOP): _C.DISABLE_VOLTAGE,  # stay in FAULT
}

#: Drive-side transitions on a controlword command (CiA 402 transitions 2-12, 16; 15 is the
#: fault-reset edge, handled by :func:`apply_controlword`). A (state, command) pair missing here
#: leaves the state unchanged. Transition 16 is included (option codes 5-8); the master's table
#: never uses it.
TRANSITIONS: dict[tuple[DriveState, Command], DriveState] = {
    (_S.SWITCH_ON_DISABLED, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,  # 2
    (_S.READY_TO_SWITCH_ON, _C.SWITCH_ON): _S.SWITCHED_ON,  # 3
    (_S.READY_TO_SWITCH_ON, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,  # 3 + 4
    (_S.SWITCHED_ON, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,  # 4
    (_S.OPERATION_ENABLED, _C.DISABLE_OPERATION): _S.SWITCHED_ON,  # 5
    (_S.SWITCHED_ON, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,  # 6
    (_S.READY_TO_SWITCH_ON, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 7
    (_S.READY_TO_SWITCH_ON, _C.QUICK_STOP): _S.SWITCH_ON_DISABLED,  # 7
    (_S.OPERATION_ENABLED, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,  # 8
    (_S.OPERATION_ENABLED, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 9
    (_S.SWITCHED_ON, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 10
    (_S.SWITCHED_ON, _C.QUICK_STOP): _S.SWITCH_ON_DISABLED,  # 10
    (_S.OPERATION_ENABLED, _C.QUICK_STOP): _S.QUICK_STOP_ACTIVE,  # 11
    (_S.QUICK_STOP_ACTIVE, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,  # 12
    (_S.QUICK_STOP_ACTIVE, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,  # 16
}


def decode_state(statusword: int) -> DriveState | None:
    """The drive state a statusword reports.

    Args:
        statusword: Object 0x6041 (u16).

    Returns:
        The state, or None when the bits match no state of CiA 402 (e.g. 0x0001).

    Safe inside the loop.
    """
    for state, (mask, value) in STATUSWORD_MASKS.items():
        if statusword & mask == value:
            return state
    return None


def decode_command(controlword: int) -> Command | None:
    """The level command a controlword carries (the fault-reset edge is not a level).

    Args:
        controlword: Object 0x6040 (u16).

    Returns:
        The command, or None for patterns CiA 402 leaves undefined (e.g. bit 7 high with 0b1111).
        ``Command.SWITCH_ON`` stands for ``DISABLE_OPERATION`` too (same bits).
    """
    for command, mask, value in CONTROLWORD_MASKS:
        if controlword & mask == value:
            return command
    return None


def apply_controlword(state: DriveState, controlword: int, previous_controlword: int) -> DriveState:
    """What a CiA 402 drive does with a controlword: the drive-side reference transitions.

    Covers the commanded transitions (2-12, 15, 16); the automatic ones (0, 1, 12 by option code,
    13, 14) belong to the drive's firmware. Used by tests and by emulators that want the
    standard's behaviour without writing it again.

    Args:
        state: Current state.
        controlword: The controlword just received.
        previous_controlword: The one received before it (for the bit 7 edge).

    Returns:
        The state after the controlword.
    """
    if state is DriveState.FAULT:
        rising = controlword & FAULT_RESET_BIT and not previous_controlword & FAULT_RESET_BIT
        return DriveState.SWITCH_ON_DISABLED if rising else state
    command = decode_command(controlword)
    if command is None:
        return state
    return TRANSITIONS.get((state, command), state)


def next_controlword(statusword: int, target: Target, previous_controlword: int = 0) -> int:
    """The controlword to send next on the way from the drive's state to ``target``.

    Args:
        statusword: The drive's latest statusword (0x6041).
        target: Where the drive should go.
        previous_controlword: The last controlword sent to this drive (for the fault-reset edge:
            0x0080 is returned only when its bit 7 is low).

    Returns:
        The controlword (u16). When the drive is already at ``target`` it is the command that
        holds it there.

    Safe inside the loop.
    """
    state = decode_state(statusword)
    if state is None:
        return int(Command.QUICK_STOP)
    command = NEXT_COMMAND[(state, target)]
    if command is Command.FAULT_RESET and previous_controlword & FAULT_RESET_BIT:
        return int(Command.DISABLE_VOLTAGE)
    return int(command)
