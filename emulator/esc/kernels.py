"""The ESC bus's arithmetic, compiled: the wire's timing, loss and corruption, the queue of transfers,
the emulated ESC nodes, the FC's node and its watch, and a stepper that flies the vehicle behind them.
`emulator.esc.bus` is the readable API over these arrays (its classes are views of them); this module
is the only place the bus model is written out.

State lives in flat float64 arrays whose layouts are the index constants below:

- ``wire`` (`W_SIZE`,): the wire, its counters and which deliveries a Python caller must see;
- ``queue`` (capacity, `Q_SIZE`): transfers in flight, a ring in the order they were sent (the wire is
  first-in first-out, so their end times never decrease);
- ``draws`` (n,): uniform numbers from the bus's generator, used in order (`W_DRAW_AT`), refilled by
  the caller: the same numbers, in the same order, as drawing them one at a time;
- ``escs`` (4 or 0, `E_SIZE`), ``health`` (4 or 0, `H_SIZE`): the ESC nodes and what the FC knows of
  each; ``fc`` (`F_SIZE`,): the FC's node, its command schedule and the stepper's counters;
- ``events`` (`EVENT_ROWS`, 4): what the nodes have to say through the FC (code, ESC index, value, t);
- ``outbox`` (`OUTBOX_ROWS`, `Q_SIZE`): transfers delivered that the caller sends to a real bus;
- ``layouts`` (`N_KINDS`, `MAX_FRAMES`) and ``n_frames`` (`N_KINDS`,): each message kind's frame
  lengths, as dronecan's transport cuts it; ``throttle`` (4,): what each ESC drives its motor at.

Message kinds carried as numbers: `RAW_COMMAND`, `ESC_STATUS`, `NODE_STATUS`; `PYTHON` is anything the
caller keeps itself (a message from Python, a frame from a real bus), keyed by its sequence number.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from emulator.fc.inner_loop import control
from emulator.fc.landed import body_landed
from emulator.physics.kernels import step_vehicle

RAW_COMMAND_MAX = 8191  # int14: full throttle
ESC_COMMAND_TIMEOUT_S = 0.1  # an ESC that hears no RawCommand this long stops its motor
NODE_STATUS_PERIOD_S = 1.0  # uavcan.protocol.NodeStatus, every node
FRAME_OVERHEAD_BITS = 67  # a 29-bit-id data frame besides its data: SOF, id, control, CRC, ACK, EOF, IFS
ERROR_FRAME_BITS = 20  # an error flag, its delimiter and the intermission
#: error frames in a row after which a transmitter gives a frame up (it would be bus-off by then: each
#: error adds 8 to its transmit error count, 256 is bus-off); the frame counts as lost
MAX_RESENDS = 32
HEALTH_OK, HEALTH_CRITICAL = 0, 2  # uavcan.protocol.NodeStatus health
AMBIENT_K = 298.15  # the air around the motors (25 C)
ESC_THERMAL_K_PER_W = 1.0  # an ESC and motor's temperature rise above the air per watt they lose

# message kinds
RAW_COMMAND, ESC_STATUS, NODE_STATUS, PYTHON = 0, 1, 2, 3
N_KINDS = 3  # kinds with a layout of their own (not PYTHON)
MAX_FRAMES = 52  # frames of one transfer (the kept ones are bits of a float64's mantissa)
PAYLOAD = 8  # payload values of a queued transfer

# wire
(W_FREE_S, W_BIT_S, W_LOSS, W_EXTRA_LOSS, W_CORRUPTION, W_BUS_OFF_UNTIL_S, W_START_S, W_FRAMES, W_BITS,
 W_BUSY_S, W_LOST, W_ERROR_FRAMES, W_BUS_OFF_DROPPED, W_SEQ, W_HEAD, W_COUNT, W_EXTERNAL_IN,
 W_EXTERNAL_OUT, W_DRAW_AT, W_BRIDGE, W_OUTBOX, W_LISTEN) = range(22)
W_SIZE = W_LISTEN + N_KINDS  # W_LISTEN + kind: a Python listener takes that kind
#: rows of ``outbox``: the compiled nodes' transfers delivered for a real bus, for the caller to send
OUTBOX_ROWS = 64
# queue columns
Q_DONE_S, Q_SEQ, Q_KIND, Q_SRC, Q_KEPT, Q_FRAMES, Q_MASK, Q_TID, Q_PRIORITY, Q_PAYLOAD = range(10)
Q_SIZE = Q_PAYLOAD + PAYLOAD
# ESC node columns
(E_INDEX, E_NODE, E_EMULATED, E_SILENT, E_LAST_COMMAND_S, E_ERRORS, E_NEXT_STATUS_S, E_NEXT_NODE_S,
 E_HEALTH, E_T0, E_TID_STATUS, E_TID_NODE) = range(12)
E_SIZE = 12
# what the FC knows of each ESC
H_LAST_S, H_ERRORS, H_RPM, H_VOLTAGE_V, H_CURRENT_A, H_TEMPERATURE_K, H_FAILED = range(7)
H_SIZE = 7
# the FC's node, its command schedule and the stepper (``F_ACTION``: an index of `config.ACTIONS`)
(F_NODE, F_T0, F_NEXT_NODE_S, F_HEALTH, F_TID_RAW, F_TID_NODE, F_COMMANDS, F_TIMEOUT_S, F_ACTION,
 F_NODES_DUE_S, F_NEXT_COMMAND_S, F_COMMAND_PERIOD_S, F_STATUS_PERIOD_S, F_MAX_ROTOR, F_POLLS,
 F_FC_STEPS, F_QUIET_STEPS, F_PHYSICS_STEPS, F_EVENTS, F_QUIET_T, F_QUIET_Z, F_QUIET_VZ, F_QUIETED,
 F_REST_Z, F_LANDED_MARGIN, F_PENDING_STEPS, F_DRAG_COEFF, F_PACK_V, F_PACK_OHM, F_EFFICIENCY) = range(30)
F_SIZE = 30
# a held offboard target a stepper may fly with the inner loop alone (`FlightController.held_target`)
T_ROLL, T_PITCH, T_YAW, T_THRUST, T_QUIET_UNTIL_S, T_ON = range(6)
T_SIZE = 6
# events for the caller
EV_ERRORS, EV_ANSWERS_AGAIN, EV_SILENT, EV_FAILSAFE = 1, 2, 3, 4
EVENT_ROWS = 32
#: events one poll of the nodes may add (the FC's watch: a report and a failsafe for each of 4 ESCs), and
#: one delivery (a status: its errors and its answering again); deliveries stop for the caller to take
#: the events before the rows could run out, so none is ever dropped
EVENTS_A_POLL, EVENTS_A_DELIVERY = 8, 2
#: draws and queue rows a caller keeps ready before a call: far more than one poll's frames can use
DRAW_RESERVE = 2048
QUEUE_RESERVE = 64
# why `run` returned
DONE, FOR_PYTHON, EVENTS, COMMAND, PHYSICS, REFILL = range(6)


def new_wire(capacity: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """An empty wire and queue."""
    wire = np.zeros(W_SIZE)
    wire[W_START_S] = math.nan
    wire[W_BUS_OFF_UNTIL_S] = -math.inf
    return wire, np.zeros((capacity, Q_SIZE))


@njit(cache=True)
def frame_bits(data_len: int) -> int:
    """Bits on the wire of an extended data frame with ``data_len`` bytes, with the stuff bits a typical
    payload needs (one in five of the stuffed part, worst case one in four)."""
    stuffed = 54 + 8 * data_len  # SOF through CRC
    return FRAME_OVERHEAD_BITS + 8 * data_len + stuffed // 5


@njit(cache=True)
def _draw(wire, draws):  # pragma: no cover
    i = int(wire[W_DRAW_AT])
    wire[W_DRAW_AT] = i + 1
    return draws[i]


@njit(cache=True)
def queue_transfer(wire, queue, draws, kind, src, tid, priority, payload, lengths, n, t):  # pragma: no cover
    """Put a transfer of ``n`` frames (data bytes ``lengths[:n]``) on the wire at ``t`` (s), behind what it
    carries: each frame may be corrupted (an error frame, then resent) or lost; a transfer short of a
    frame never completes, its other frames still pass. Returns its sequence number, -1 if no frame of
    it reaches a receiver."""
    if math.isnan(wire[W_START_S]):
        wire[W_START_S] = t
    if t < wire[W_BUS_OFF_UNTIL_S]:
        wire[W_BUS_OFF_DROPPED] += n
        return -1
    loss = wire[W_LOSS] if wire[W_LOSS] > wire[W_EXTRA_LOSS] else wire[W_EXTRA_LOSS]
    corruption, bit_s = wire[W_CORRUPTION], wire[W_BIT_S]
    start = t if t > wire[W_FREE_S] else wire[W_FREE_S]
    mask = 0.0
    kept = 0
    for i in range(n):
        bits = frame_bits(lengths[i])
        resends = 0
        gave_up = False
        while corruption > 0 and _draw(wire, draws) < corruption:  # error frame, then resent
            wire[W_ERROR_FRAMES] += 1
            start += (bits // 2 + ERROR_FRAME_BITS) * bit_s
            resends += 1
            if resends >= MAX_RESENDS:
                gave_up = True
                break
        if gave_up:
            wire[W_LOST] += 1
            continue
        done = start + bits * bit_s
        wire[W_BITS] += bits
        wire[W_BUSY_S] += done - start
        start = done
        if loss > 0 and _draw(wire, draws) < loss:
            wire[W_LOST] += 1
            continue
        kept += 1
        mask += 2.0**i
    wire[W_FREE_S] = start
    if kept == 0:
        return -1
    cap = queue.shape[0]
    count = int(wire[W_COUNT])
    row = queue[(int(wire[W_HEAD]) + count) % cap]
    wire[W_COUNT] = count + 1
    wire[W_SEQ] += 1
    row[Q_DONE_S], row[Q_SEQ], row[Q_KIND], row[Q_SRC] = start, wire[W_SEQ], kind, src
    row[Q_KEPT], row[Q_FRAMES], row[Q_MASK], row[Q_TID], row[Q_PRIORITY] = kept, n, mask, tid, priority
    for j in range(PAYLOAD):
        row[Q_PAYLOAD + j] = payload[j] if j < payload.shape[0] else 0.0
    return int(wire[W_SEQ])


@njit(cache=True)
def head_done_s(wire, queue):  # pragma: no cover
    """When the transfer at the head of the queue is off the wire (s); inf when none is."""
    if wire[W_COUNT] == 0:
        return math.inf
    return queue[int(wire[W_HEAD]), Q_DONE_S]


@njit(cache=True)
def pop_head(wire, queue, out):  # pragma: no cover
    """Take the head transfer off the queue into ``out`` (`Q_SIZE`,), its frames counted delivered."""
    head = int(wire[W_HEAD])
    out[:] = queue[head]
    wire[W_HEAD] = (head + 1) % queue.shape[0]
    wire[W_COUNT] -= 1
    wire[W_FRAMES] += out[Q_KEPT]


@njit(cache=True)
def _event(fc, events, code, index, value, t):  # pragma: no cover
    k = int(fc[F_EVENTS])  # (room by construction: `deliver` stops while a poll's worth is left)
    events[k, 0], events[k, 1], events[k, 2], events[k, 3] = code, index, value, t
    fc[F_EVENTS] = k + 1


@njit(cache=True)
def esc_on_command(escs, throttle, src, cmd, n_cmd, t):  # pragma: no cover
    """A RawCommand from node ``src`` reaches the emulated ESCs: each takes its channel of ``cmd[:n_cmd]``."""
    for r in range(escs.shape[0]):
        e = escs[r]
        if e[E_EMULATED] == 0 or e[E_SILENT] != 0 or e[E_NODE] == src:
            continue
        i = int(e[E_INDEX])
        if i < n_cmd:
            c = int(cmd[i])
            throttle[i] = (c if c > 0 else 0) / RAW_COMMAND_MAX
            e[E_LAST_COMMAND_S] = t


@njit(cache=True)
def fc_on_status(health, fc, events, src, p, t):  # pragma: no cover
    """An esc.Status (`ESC_STATUS` payload ``p``) from node ``src`` reaches the FC's node."""
    if fc[F_NODE] < 0 or fc[F_NODE] == src:
        return
    index = int(p[6])
    if not 0 <= index < health.shape[0]:
        return
    h = health[index]
    errors = p[0]
    if errors > h[H_ERRORS]:
        _event(fc, events, EV_ERRORS, index, errors, t)
    h[H_LAST_S], h[H_ERRORS], h[H_RPM] = t, errors, p[4]
    h[H_VOLTAGE_V], h[H_CURRENT_A], h[H_TEMPERATURE_K] = p[1], p[2], p[3]
    if h[H_FAILED] != 0:
        h[H_FAILED] = 0.0
        _event(fc, events, EV_ANSWERS_AGAIN, index, 0.0, t)
        any_failed = False
        for j in range(health.shape[0]):
            any_failed = any_failed or health[j, H_FAILED] != 0
        if not any_failed:
            fc[F_HEALTH] = HEALTH_OK


@njit(cache=True)
def hand_to_nodes(escs, health, fc, events, throttle, kind, src, payload, t):  # pragma: no cover
    """A complete transfer of ``kind`` reaches this process's compiled nodes."""
    if kind == RAW_COMMAND:
        esc_on_command(escs, throttle, src, payload, int(payload[PAYLOAD - 1]), t)
    elif kind == ESC_STATUS:
        fc_on_status(health, fc, events, src, payload, t)


@njit(cache=True)
def _needs_caller(wire, row):  # pragma: no cover
    kind = int(row[Q_KIND])
    return kind == PYTHON or wire[W_LISTEN + kind] != 0


@njit(cache=True)
def deliver(wire, queue, escs, health, fc, events, outbox, throttle, t):  # pragma: no cover
    """Hand on every transfer off the wire by ``t`` (s) to the compiled nodes, and with a real bus
    (``W_BRIDGE``) copy it to ``outbox`` (``W_OUTBOX`` rows) for the caller to send. Returns `DONE`,
    or stops for the caller: `FOR_PYTHON` at a transfer it must see first (`_needs_caller`: it pops
    that one itself), `EVENTS` when the events or the outbox must be taken before more can come."""
    tmp = np.empty(Q_SIZE)
    while wire[W_COUNT] > 0:
        row = queue[int(wire[W_HEAD])]
        if row[Q_DONE_S] > t + 1e-12:
            return DONE
        if _needs_caller(wire, row):
            return FOR_PYTHON
        if fc[F_EVENTS] > EVENT_ROWS - EVENTS_A_POLL - EVENTS_A_DELIVERY:
            return EVENTS
        bridged = wire[W_BRIDGE] != 0
        if bridged and wire[W_OUTBOX] >= outbox.shape[0]:
            return EVENTS
        pop_head(wire, queue, tmp)
        if bridged:
            outbox[int(wire[W_OUTBOX])] = tmp
            wire[W_OUTBOX] += 1
        if tmp[Q_KEPT] == tmp[Q_FRAMES]:  # complete
            hand_to_nodes(escs, health, fc, events, throttle, int(tmp[Q_KIND]), tmp[Q_SRC],
                          tmp[Q_PAYLOAD:], tmp[Q_DONE_S])
    return DONE


@njit(cache=True)
def _broadcast(wire, queue, draws, layouts, n_frames, kind, src, tid, priority, payload,
               t):  # pragma: no cover
    queue_transfer(wire, queue, draws, kind, src, tid, priority, payload, layouts[kind], n_frames[kind], t)


@njit(cache=True)
def _node_status(wire, queue, draws, layouts, n_frames, src, t0, health_code, next_s, tid,
                 t):  # pragma: no cover
    """NodeStatus at 1 Hz from one node; returns its next time and transfer id."""
    p = np.zeros(PAYLOAD)
    while t >= next_s - 1e-12:
        p[0], p[1] = int(t - t0), health_code
        _broadcast(wire, queue, draws, layouts, n_frames, NODE_STATUS, src, tid, 24, p, t)
        tid = (tid + 1) & 31
        next_s += NODE_STATUS_PERIOD_S
    return next_s, tid


@njit(cache=True)
def esc_due_s(e, throttle):  # pragma: no cover
    """When an ESC node has something to do next (s): a status, a NodeStatus, or the command timeout."""
    due = e[E_NEXT_STATUS_S] if e[E_NEXT_STATUS_S] < e[E_NEXT_NODE_S] else e[E_NEXT_NODE_S]
    timeout_s = e[E_LAST_COMMAND_S] + ESC_COMMAND_TIMEOUT_S
    if throttle[int(e[E_INDEX])] != 0.0 and timeout_s < due:
        due = timeout_s
    return due


@njit(cache=True)
def esc_power(fc, rotor_w, i):  # pragma: no cover
    """What ESC ``i`` reports of its power train with the rotors at ``rotor_w`` (rad/s, all four): (pack
    voltage V, its current A, its temperature K, its power in % of its motor's full power).

    The model: a rotor's shaft power is its drag torque times its speed, k_m |w|^3 (k_m, the profile's
    ``drag_torque_coeff_nm_s2``); the ESC draws that over the power train's efficiency (the profile's
    ``motor_efficiency``). The pack (open-circuit ``battery_voltage_v``, internal
    ``battery_resistance_ohm``) feeds the four: its voltage V solves V = V_oc - R P_total / V (the sag
    under the total draw; half V_oc past the pack's maximum power), and each ESC's current is its power
    over V. Its temperature is the air's plus `ESC_THERMAL_K_PER_W` per watt lost, at once (no thermal
    lag); its power % is its draw over the draw at full rotor speed (``F_MAX_ROTOR``)."""
    km, eff = fc[F_DRAG_COEFF], fc[F_EFFICIENCY]
    total = 0.0
    for j in range(rotor_w.shape[0]):
        total += km * abs(rotor_w[j]) ** 3 / eff
    own = km * abs(rotor_w[i]) ** 3 / eff
    v_oc, ohm = fc[F_PACK_V], fc[F_PACK_OHM]
    disc = v_oc * v_oc - 4.0 * ohm * total
    volts = 0.5 * (v_oc + math.sqrt(disc)) if disc > 0.0 else 0.5 * v_oc
    full = km * fc[F_MAX_ROTOR] ** 3 / eff
    pct = 100.0 * own / full if full > 0.0 else 0.0
    amps = own / volts if volts > 0.0 else 0.0
    return volts, amps, AMBIENT_K + ESC_THERMAL_K_PER_W * (1.0 - eff) * own, pct


@njit(cache=True)
def esc_poll(wire, queue, draws, layouts, n_frames, fc, e, throttle, t, rotor_w):  # pragma: no cover
    """One emulated ESC at ``t`` (s): its command timeout, NodeStatus and esc.Status (rpm from its
    rotor's speed and its power train from all four, ``rotor_w`` (4,), rad/s: `esc_power`). A silent
    one stops its motor and lets its slots pass."""
    i = int(e[E_INDEX])
    period_s = fc[F_STATUS_PERIOD_S]
    if e[E_SILENT] != 0:
        throttle[i] = 0.0
        while t >= e[E_NEXT_STATUS_S] - 1e-12:
            e[E_NEXT_STATUS_S] += period_s
        while t >= e[E_NEXT_NODE_S] - 1e-12:
            e[E_NEXT_NODE_S] += NODE_STATUS_PERIOD_S
        return
    if t - e[E_LAST_COMMAND_S] > ESC_COMMAND_TIMEOUT_S and throttle[i] != 0.0:
        throttle[i] = 0.0  # the command stream stopped: the motor stops
        e[E_ERRORS] += 1
    src = e[E_NODE]
    e[E_NEXT_NODE_S], e[E_TID_NODE] = _node_status(wire, queue, draws, layouts, n_frames, src, e[E_T0],
                                                   e[E_HEALTH], e[E_NEXT_NODE_S], int(e[E_TID_NODE]), t)
    if t >= e[E_NEXT_STATUS_S] - 1e-12:
        p = np.zeros(PAYLOAD)  # (in the order of `esc_bus.STATUS_FIELDS`)
        p[0] = e[E_ERRORS]
        p[1], p[2], p[3], pct = esc_power(fc, rotor_w, i)
        rpm = rotor_w[i] * 60.0 / (2.0 * math.pi)
        p[4] = int(rpm) if abs(rpm) < 1e9 else 0  # (a diverged rotor: no number to report)
        p[5], p[6] = min(127.0, np.rint(pct)), i  # (uint7)
        tid = int(e[E_TID_STATUS])
        _broadcast(wire, queue, draws, layouts, n_frames, ESC_STATUS, src, tid, 16, p, t)
        e[E_TID_STATUS] = (tid + 1) & 31
        e[E_NEXT_STATUS_S] += period_s
        if e[E_NEXT_STATUS_S] <= t:
            e[E_NEXT_STATUS_S] = t + period_s


@njit(cache=True)
def fc_due_s(health, fc):  # pragma: no cover
    """When the FC's node has something to do next (s): its NodeStatus or an ESC's status timeout."""
    due = fc[F_NEXT_NODE_S]
    timeout_s = fc[F_TIMEOUT_S]
    for j in range(health.shape[0]):
        h = health[j]
        if h[H_FAILED] == 0 and h[H_LAST_S] + timeout_s < due:
            due = h[H_LAST_S] + timeout_s
    return due


@njit(cache=True)
def fc_poll(wire, queue, draws, layouts, n_frames, health, fc, events, t, armed):  # pragma: no cover
    """The FC's node at ``t`` (s): its NodeStatus and its watch over each ESC's esc.Status (a silent one
    reported failed, and the failsafe when configured and armed)."""
    fc[F_NEXT_NODE_S], fc[F_TID_NODE] = _node_status(wire, queue, draws, layouts, n_frames, fc[F_NODE],
                                                     fc[F_T0], fc[F_HEALTH], fc[F_NEXT_NODE_S],
                                                     int(fc[F_TID_NODE]), t)
    timeout_s = fc[F_TIMEOUT_S]
    for j in range(health.shape[0]):
        h = health[j]
        if h[H_FAILED] == 0 and t - h[H_LAST_S] > timeout_s:
            h[H_FAILED] = 1.0
            fc[F_HEALTH] = HEALTH_CRITICAL
            _event(fc, events, EV_SILENT, j, timeout_s, t)
            if armed and fc[F_ACTION] != 0:
                _event(fc, events, EV_FAILSAFE, j, fc[F_ACTION], t)


@njit(cache=True)
def poll(wire, queue, draws, escs, health, fc, events, outbox, layouts, n_frames, throttle, rotor_w, t,
         armed):  # pragma: no cover
    """Everything due by ``t`` (s): transfers delivered, the nodes' reports, the FC's watch, the motors of
    ESCs outside this process (they follow the rpm they report). Returns `FOR_PYTHON` when a delivery
    waits for the caller (the nodes are polled after it, at the next call), `EVENTS` when the nodes
    have something to say (or must be heard before more is delivered), else `DONE`."""
    why = deliver(wire, queue, escs, health, fc, events, outbox, throttle, t)
    if why != DONE:
        return why
    if t >= fc[F_NODES_DUE_S] - 1e-12:
        due = math.inf
        for r in range(escs.shape[0]):
            e = escs[r]
            if e[E_EMULATED] == 0:
                continue
            d = esc_due_s(e, throttle)
            if t >= d - 1e-12 or e[E_SILENT] != 0:
                esc_poll(wire, queue, draws, layouts, n_frames, fc, e, throttle, t, rotor_w)
                d = esc_due_s(e, throttle)
            due = d if d < due else due
        if fc[F_NODE] >= 0:
            d = fc_due_s(health, fc)
            if t >= d - 1e-12:
                fc_poll(wire, queue, draws, layouts, n_frames, health, fc, events, t, armed)
                d = fc_due_s(health, fc)
            due = d if d < due else due
        fc[F_NODES_DUE_S] = due
    max_w = fc[F_MAX_ROTOR]
    for r in range(escs.shape[0]):
        if escs[r, E_EMULATED] == 0:  # an outside ESC's motor follows the rpm it reports
            i = int(escs[r, E_INDEX])
            w = health[i, H_RPM] * 2.0 * math.pi / 60.0
            u = w / max_w
            u = u if u > 0.0 else 0.0
            u = u**2
            throttle[i] = u if u < 1.0 else 1.0
    return EVENTS if fc[F_EVENTS] > 0 else DONE


@njit(cache=True)
def next_event_s(wire, queue, fc):  # pragma: no cover
    """When the bus or a node next has something to do (s). The nodes' times are those of the last poll:
    a status coming in only moves the FC's watch later, and a command due at an ESC arrives on the bus,
    whose own time is always current."""
    head = head_done_s(wire, queue)
    return head if head < fc[F_NODES_DUE_S] else fc[F_NODES_DUE_S]


@njit(cache=True)
def send_command(wire, queue, draws, layouts, n_frames, fc, throttles, t):  # pragma: no cover
    """RawCommand from the FC's motor outputs ``throttles`` (4,) in [0, 1] at ``t`` (s)."""
    p = np.zeros(PAYLOAD)
    n = throttles.shape[0]
    for i in range(n):
        c = np.rint(throttles[i] * RAW_COMMAND_MAX)
        p[i] = RAW_COMMAND_MAX if c > RAW_COMMAND_MAX else (c if c > 0 else 0.0)
    p[PAYLOAD - 1] = n
    tid = int(fc[F_TID_RAW])
    fc[F_TID_RAW] = (tid + 1) & 31
    _broadcast(wire, queue, draws, layouts, n_frames, RAW_COMMAND, fc[F_NODE], tid, 8, p, t)
    fc[F_COMMANDS] += 1


@njit(cache=True)
def command(wire, queue, draws, escs, health, fc, events, outbox, layouts, n_frames, throttle, throttles,
            t):  # pragma: no cover
    """The FC's motor tick at ``t`` (s): its outputs ``throttles`` sent, its next tick scheduled, what is
    due delivered. Returns what `deliver` stops for, `EVENTS` when the nodes have something to say, else
    `DONE`."""
    send_command(wire, queue, draws, layouts, n_frames, fc, throttles, t)
    fc[F_FC_STEPS] += 1
    fc[F_NEXT_COMMAND_S] += fc[F_COMMAND_PERIOD_S]
    if fc[F_NEXT_COMMAND_S] <= t:
        fc[F_NEXT_COMMAND_S] = t + fc[F_COMMAND_PERIOD_S]
    why = deliver(wire, queue, escs, health, fc, events, outbox, throttle, t)
    if why != DONE:
        return why
    return EVENTS if fc[F_EVENTS] > 0 else DONE


@njit(cache=True)
def _quiet_command(fc, target, x, t, dt):  # pragma: no cover
    """Whether the FC's motor tick at ``t`` may be its inner loop alone on the held target: in OFFBOARD
    with no timed change before the step (`FlightController.quiet_steps`) and the body not landed by
    the FC's test (`FlightController.detect_landed`: a landing is the FC's own step's to see)."""
    if target[T_ON] == 0:
        return False
    room = target[T_QUIET_UNTIL_S] - t
    if not (room > 0 and int(room / dt) >= 1):
        return False
    return not body_landed(x[2], x[5], fc[F_REST_Z], fc[F_LANDED_MARGIN])


@njit(cache=True)
def run(x, aux, p, native, wire, queue, draws, escs, health, fc, events, outbox, layouts, n_frames, throttle,
        target, gains, mix_inv, motor_out, n_steps, t0, steps0, dt, armed):  # pragma: no cover
    """Step the vehicle (state row ``x``, ``aux``, parameters ``p``: `NativeBackend.kernel_arrays`) with
    its motors behind the bus for up to ``n_steps`` physics steps of ``dt`` (s) from step ``steps0`` of a
    clock started at ``t0`` (s): the bus and its nodes polled at their events, the FC's motor tick at
    its rate (its inner loop on the held ``target`` while `_quiet_command`, writing ``motor_out``),
    the physics between them with each motor at its ESC's ``throttle``. Without ``native`` physics it
    takes no step: it leaves the steps to take in ``fc[F_PENDING_STEPS]`` and returns `PHYSICS`.
    Returns (steps taken, why it stopped: `DONE`, or what the caller must do first: `FOR_PYTHON`,
    `EVENTS`, `COMMAND` (the FC's own update for this tick), `PHYSICS`, `REFILL` (draws, queue room))."""
    taken = 0
    while taken < n_steps:
        t = t0 + (steps0 + taken) * dt  # (`NativeBackend.time_s`)
        if wire[W_DRAW_AT] > draws.shape[0] - DRAW_RESERVE or wire[W_COUNT] + QUEUE_RESERVE > queue.shape[0]:
            return taken, REFILL
        event_s = next_event_s(wire, queue, fc)
        if t >= event_s - 1e-9:
            fc[F_POLLS] += 1
            why = poll(wire, queue, draws, escs, health, fc, events, outbox, layouts, n_frames, throttle,
                       x[13:17], t, armed)
            if why != DONE:
                return taken, why
            event_s = next_event_s(wire, queue, fc)
        if t >= fc[F_NEXT_COMMAND_S] - 1e-9:
            if not _quiet_command(fc, target, x, t, dt):
                return taken, COMMAND
            control(x[6:10], x[10:13], target[T_ROLL], target[T_PITCH], target[T_YAW], target[T_THRUST],
                    gains, mix_inv, motor_out)
            fc[F_QUIET_T], fc[F_QUIET_Z], fc[F_QUIET_VZ], fc[F_QUIETED] = t, x[2], x[5], 1.0
            fc[F_QUIET_STEPS] += 1
            why = command(wire, queue, draws, escs, health, fc, events, outbox, layouts, n_frames, throttle,
                          motor_out, t)
            if why != DONE:
                return taken, why
            event_s = next_event_s(wire, queue, fc)
        until = fc[F_NEXT_COMMAND_S] if fc[F_NEXT_COMMAND_S] < event_s else event_s
        k = math.ceil((until - t) / dt - 1e-6)
        k = min(n_steps - taken, k)
        k = max(1, k)
        if not native:
            fc[F_PENDING_STEPS] = k
            return taken, PHYSICS
        step_vehicle(x, aux, p, throttle, k)
        fc[F_PHYSICS_STEPS] += k
        taken += k
    return taken, DONE
