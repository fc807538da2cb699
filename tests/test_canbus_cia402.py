"""CiA 402 state machine table: decoding, every transition 0-16, fault and fault reset.

The expected controlwords and statuswords are written out here from CiA 402 (IEC 61800-7-201)
"state machine" and "device control commands", independently of the module's tables.
"""

from __future__ import annotations

import itertools

import pytest

from rt_runtime.canbus.cia402 import (
    NEXT_COMMAND,
    Command,
    DriveState,
    Target,
    apply_controlword,
    decode_command,
    decode_state,
    next_controlword,
)

S = DriveState

# Typical statuswords a drive sends (bit 9 remote and bit 4 voltage enabled set where a drive
# would set them); the state bits are CiA 402 Table "state coding".
STATUSWORD = {
    S.NOT_READY_TO_SWITCH_ON: 0x0200,
    S.SWITCH_ON_DISABLED: 0x0250,
    S.READY_TO_SWITCH_ON: 0x0231,
    S.SWITCHED_ON: 0x0233,
    S.OPERATION_ENABLED: 0x0237,
    S.QUICK_STOP_ACTIVE: 0x0217,
    S.FAULT_REACTION_ACTIVE: 0x021F,
    S.FAULT: 0x0218,
}

# CiA 402 transitions with a command: (number, from, controlword, to).
COMMANDED = [
    (2, S.SWITCH_ON_DISABLED, 0x0006, S.READY_TO_SWITCH_ON),
    (3, S.READY_TO_SWITCH_ON, 0x0007, S.SWITCHED_ON),
    (4, S.SWITCHED_ON, 0x000F, S.OPERATION_ENABLED),
    (5, S.OPERATION_ENABLED, 0x0007, S.SWITCHED_ON),
    (6, S.SWITCHED_ON, 0x0006, S.READY_TO_SWITCH_ON),
    (7, S.READY_TO_SWITCH_ON, 0x0000, S.SWITCH_ON_DISABLED),
    (7, S.READY_TO_SWITCH_ON, 0x0002, S.SWITCH_ON_DISABLED),
    (8, S.OPERATION_ENABLED, 0x0006, S.READY_TO_SWITCH_ON),
    (9, S.OPERATION_ENABLED, 0x0000, S.SWITCH_ON_DISABLED),
    (10, S.SWITCHED_ON, 0x0000, S.SWITCH_ON_DISABLED),
    (10, S.SWITCHED_ON, 0x0002, S.SWITCH_ON_DISABLED),
    (11, S.OPERATION_ENABLED, 0x0002, S.QUICK_STOP_ACTIVE),
    (12, S.QUICK_STOP_ACTIVE, 0x0000, S.SWITCH_ON_DISABLED),
    (16, S.QUICK_STOP_ACTIVE, 0x000F, S.OPERATION_ENABLED),
]

# Automatic transitions the drive makes by itself (0, 1, 12 with option code 2, 13, 14).
AUTOMATIC = {
    S.NOT_READY_TO_SWITCH_ON: S.SWITCH_ON_DISABLED,  # 1
    S.FAULT_REACTION_ACTIVE: S.FAULT,  # 14
}


def test_canonical_statuswords_decode() -> None:
    for state, word in STATUSWORD.items():
        assert decode_state(word) is state, hex(word)
        # Bits outside the state bits (4, 7, 8-15) never change the state.
        for extra in (0x0010, 0x0080, 0x0100, 0x0400, 0x8000, 0xFF90):
            assert decode_state(word | extra) is state, hex(word | extra)


def test_every_statusword_decodes_to_at_most_one_state() -> None:
    undecodable = 0
    for word in range(0x10000):
        state = decode_state(word)
        undecodable += state is None
        # Independent check from the standard's bit patterns (x = don't care).
        low = word & 0x6F
        expected = {
            0x00: S.NOT_READY_TO_SWITCH_ON,
            0x20: S.NOT_READY_TO_SWITCH_ON,
            0x40: S.SWITCH_ON_DISABLED,
            0x60: S.SWITCH_ON_DISABLED,
            0x21: S.READY_TO_SWITCH_ON,
            0x23: S.SWITCHED_ON,
            0x27: S.OPERATION_ENABLED,
            0x07: S.QUICK_STOP_ACTIVE,
            0x0F: S.FAULT_REACTION_ACTIVE,
            0x2F: S.FAULT_REACTION_ACTIVE,
            0x08: S.FAULT,
            0x28: S.FAULT,
        }.get(low)
        assert state is expected, f"statusword 0x{word:04X}: {state} != {expected}"
    # 0b0001 without quick stop, or with bit 6, and similar patterns are not states.
    assert undecodable > 0
    assert decode_state(0x0001) is None
    assert decode_state(0x0067) is None


@pytest.mark.parametrize(("number", "start", "word", "end"), COMMANDED)
def test_commanded_transition(number: int, start: DriveState, word: int, end: DriveState) -> None:
    assert apply_controlword(start, word, previous_controlword=0) is end, number


def test_command_patterns() -> None:
    assert Command.SHUTDOWN == 0x0006
    assert Command.SWITCH_ON == 0x0007
    assert Command.DISABLE_OPERATION == 0x0007
    assert Command.ENABLE_OPERATION == 0x000F
    assert Command.DISABLE_VOLTAGE == 0x0000
    assert Command.QUICK_STOP == 0x0002
    assert Command.FAULT_RESET == 0x0080
    # Don't-care bits per the command table.
    assert decode_command(0x000E) is Command.SHUTDOWN  # 0 x 1 1 0
    assert decode_command(0x0005) is Command.DISABLE_VOLTAGE  # 0 x x 0 x
    assert decode_command(0x000B) is Command.QUICK_STOP  # 0 x 0 1 x
    assert decode_command(0x008F) is None  # bit 7 high: no level command


def test_fault_and_fault_reset_edge() -> None:
    # 13, 14: only the drive itself goes to FAULT; no controlword leads there.
    for state, word, previous in itertools.product(S, range(0x100), (0x00, 0x80)):
        if state not in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            assert apply_controlword(state, word, previous) not in (
                S.FAULT,
                S.FAULT_REACTION_ACTIVE,
            )
    # 15: only a 0 -> 1 edge of bit 7 resets.
    assert apply_controlword(S.FAULT, 0x0080, previous_controlword=0x0000) is S.SWITCH_ON_DISABLED
    assert apply_controlword(S.FAULT, 0x0080, previous_controlword=0x0080) is S.FAULT
    assert apply_controlword(S.FAULT, 0x0000, previous_controlword=0x0080) is S.FAULT
    assert apply_controlword(S.FAULT, 0x000F, previous_controlword=0x0000) is S.FAULT
    # The table alternates 0x80 / 0x00 while the drive stays in FAULT.
    fault = STATUSWORD[S.FAULT]
    words = []
    previous = 0x000F
    for _ in range(5):
        previous = next_controlword(fault, Target.OPERATION_ENABLED, previous)
        words.append(previous)
    assert words == [0x0080, 0x0000, 0x0080, 0x0000, 0x0080]
    # Starting from a previous word with bit 7 high, the first word primes the edge.
    assert next_controlword(fault, Target.DISABLED, 0x0080) == 0x0000
    # QUICK_STOP never resets a fault.
    for previous in (0x0000, 0x0080, 0x000F):
        assert next_controlword(fault, Target.QUICK_STOP, previous) & 0x0080 == 0


def test_table_is_total() -> None:
    assert set(NEXT_COMMAND) == set(itertools.product(S, Target))


def _drive(start: DriveState, target: Target, max_steps: int = 8) -> list[DriveState]:
    """Run the master's table against the standard's drive behaviour; the visited states."""
    state, previous, path = start, 0x0000, [start]
    for _ in range(max_steps):
        state = AUTOMATIC.get(state, state)
        word = next_controlword(STATUSWORD[state], target, previous)
        state = apply_controlword(state, word, previous)
        previous = word
        path.append(state)
    return path


# Where each target ends, from each start (QUICK_STOP from OPERATION_ENABLED stops in
# QUICK_STOP_ACTIVE; the drive's own transition 12 follows; from FAULT it stays).
def _end(start: DriveState, target: Target) -> DriveState:
    if target is Target.OPERATION_ENABLED:
        return S.OPERATION_ENABLED
    if target is Target.SWITCHED_ON:
        return S.SWITCHED_ON
    if target is Target.DISABLED:
        return S.SWITCH_ON_DISABLED
    if start is S.OPERATION_ENABLED or start is S.QUICK_STOP_ACTIVE:
        return S.QUICK_STOP_ACTIVE
    if start in (S.FAULT, S.FAULT_REACTION_ACTIVE):
        return S.FAULT
    return S.SWITCH_ON_DISABLED


@pytest.mark.parametrize(("start", "target"), list(itertools.product(S, Target)))
def test_every_state_reaches_every_target(start: DriveState, target: Target) -> None:
    path = _drive(start, target)
    end = _end(start, target)
    assert path[-1] is end, f"{start.name} -> {target.name}: {[s.name for s in path]}"
    # Once there, it stays (the table's "hold" command).
    assert path[-2] is end
    if target is not Target.OPERATION_ENABLED:
        # Stopping never passes through OPERATION_ENABLED.
        assert S.OPERATION_ENABLED not in path[1:]
    if target is Target.QUICK_STOP and start in (S.FAULT, S.FAULT_REACTION_ACTIVE):
        assert S.SWITCH_ON_DISABLED not in path


def test_paths_use_the_documented_transitions() -> None:
    # Up: 2, 3, 4.
    assert _drive(S.SWITCH_ON_DISABLED, Target.OPERATION_ENABLED)[:4] == [
        S.SWITCH_ON_DISABLED,
        S.READY_TO_SWITCH_ON,
        S.SWITCHED_ON,
        S.OPERATION_ENABLED,
    ]
    # Down: 5 then 10, never 9.
    assert _drive(S.OPERATION_ENABLED, Target.DISABLED)[:3] == [
        S.OPERATION_ENABLED,
        S.SWITCHED_ON,
        S.SWITCH_ON_DISABLED,
    ]
    # Quick stop: 11.
    assert _drive(S.OPERATION_ENABLED, Target.QUICK_STOP)[:2] == [
        S.OPERATION_ENABLED,
        S.QUICK_STOP_ACTIVE,
    ]
    # From FAULT: 15, 2, 3, 4.
    assert _drive(S.FAULT, Target.OPERATION_ENABLED)[:5] == [
        S.FAULT,
        S.SWITCH_ON_DISABLED,
        S.READY_TO_SWITCH_ON,
        S.SWITCHED_ON,
        S.OPERATION_ENABLED,
    ]


def test_undecodable_statusword_gets_quick_stop() -> None:
    for target in Target:
        assert next_controlword(0x0001, target, 0x000F) == 0x0002
