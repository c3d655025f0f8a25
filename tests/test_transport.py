"""The headless neighbour transport and the radio model it shares with the SITL's medium."""
import math

import numpy as np

from companion.swarm import FLAG_OWN_VALID, SwarmStates, SwarmView
from sim_bridge.world.transport import LinkConfig, LossyTransport, RadioModel, hashed_uniform


def _reference(cfg: LinkConfig, seed, sender, stamp_s, send_s, sender_pos, receiver_pos):
    """RadioModel.deliveries written with numpy over hashed_uniform (the definition)."""
    k, n = len(sender), len(receiver_pos)
    msg, rcv = np.meshgrid(np.arange(k), np.arange(n), indexing="ij")
    keep = rcv != sender[:, None]
    if cfg.range_m is not None:
        keep &= np.linalg.norm(sender_pos[:, None] - receiver_pos[None], axis=2) <= cfg.range_m
    stamp_us = np.round(stamp_s * 1e6)[:, None]
    keep &= hashed_uniform(seed, sender[:, None], stamp_us, rcv, 1) >= cfg.loss
    when = send_s + cfg.delay_s + cfg.jitter_s * hashed_uniform(seed, sender[:, None], stamp_us, rcv, 2)
    return msg[keep], rcv[keep], when[keep]


def test_compiled_fates_equal_the_hashed_uniform_definition():
    rng = np.random.default_rng(5)
    for cfg in (LinkConfig(kind="lossy", loss=0.3, delay_s=0.1, jitter_s=0.05),
                LinkConfig(kind="lossy", loss=0.2, delay_s=0.02, range_m=40.0)):
        radio = RadioModel(cfg, 2024)
        for t in range(20):
            sender = rng.choice(40, 8, replace=False)
            stamp = np.round(rng.uniform(0, 200, 8), 2)
            pos = rng.uniform(-50, 50, (40, 3))
            got = radio.deliveries(sender, stamp, t * 0.02, pos[sender], pos)
            ref = _reference(cfg, 2024, sender, stamp, t * 0.02, pos[sender], pos)
            for a, b in zip(got, ref):
                np.testing.assert_array_equal(a, b)


def test_loss_rate_is_the_configured_one_and_a_seed_repeats_it():
    cfg = LinkConfig(kind="lossy", loss=0.1, delay_s=0.1)
    sender = np.arange(40)
    counts = []
    for seed in (1, 1, 2):
        radio = RadioModel(cfg, seed)
        counts.append(sum(len(radio.deliveries(sender, np.full(40, t * 0.1), t * 0.1, np.zeros((40, 3)),
                                               np.zeros((40, 3)))[0]) for t in range(200)))
    total = 200 * 40 * 39
    assert counts[0] == counts[1] != counts[2]
    assert abs(1 - counts[0] / total - 0.1) < 0.005  # 312,000 copies: 3 sigma is 0.16 %


def _states(ids, t):
    k = len(ids)
    return SwarmStates(np.asarray(ids), np.full(k, t), np.tile([float(t), 0.0, 0.0], (k, 1)), np.zeros((k, 3)),
                       np.tile([1.0, 0, 0, 0], (k, 1)), np.zeros(k, np.int8), np.full(k, FLAG_OWN_VALID, np.uint8),
                       np.full(k, math.nan))


def test_lossy_transport_delivers_after_the_delay_and_splits_jittered_chunks():
    n = 5
    for jitter in (0.0, 0.04):
        tr = LossyTransport(n, LinkConfig(kind="lossy", loss=0.0, delay_s=0.1, jitter_s=jitter), seed=3)
        view = SwarmView.unknown(n, n)
        tr.publish(1.0, _states([0, 1], 1.0), np.zeros((n, 3)))
        tr.deliver(1.0999, view)
        assert np.isnan(view.stamp_s).all()  # nothing before the delay
        t, seen = 1.1, []
        while t < 1.16:
            tr.deliver(t, view)
            seen.append(int(np.isfinite(view.stamp_s).sum()))
            t += 0.005
        assert seen[-1] == 2 * (n - 1)  # every copy, each once (a vehicle never hears itself)
        assert (len(set(seen)) > 2) == (jitter > 0)  # jitter: copies trickle in
        assert tr.delivered == 2 * (n - 1) and tr.sent == 2 * (n - 1)
        assert np.isnan(view.stamp_s[0, 0]) and np.isnan(view.stamp_s[1, 1])


def test_sitl_radio_drops_a_state_with_an_unknown_phase():
    """A hostile SWARMDROP_STATE (phase 200) must neither raise nor land in the recorder."""
    import socket
    import time

    from companion.link.msgdef import swarmdrop as sd
    from sim_bridge.sitl.medium import Medium

    md = Medium(3, LinkConfig(), seed=1, epoch_unix_s=0.0, bind=("127.0.0.1", 0))
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for stamp_us, phase in ((1_000_000, 200), (2_000_000, 3)):
            msg = sd.MAVLink_swarmdrop_state_message(stamp_us, 0, 0, 0, -10, 0, 0, 0, [1, 0, 0, 0], phase, 2, 1)
            tx.sendto(msg.pack(sd.MAVLink(None, srcSystem=2, srcComponent=191)), ("127.0.0.1", md.port))
        deadline = time.monotonic() + 5.0
        while md.bad_frames + int(md.states_in.sum()) < 2 and time.monotonic() < deadline:
            md.receive()  # non-blocking: polled with a deadline until both datagrams are in
        assert md.bad_frames == 1 and md.states_in.tolist() == [0, 1, 0]
        assert md.phase.tolist() == [0, 3, 0] and md.latest_stamp_us[1] == 2_000_000
    finally:
        tx.close()
        md.close()
