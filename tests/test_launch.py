"""warpsim.core.launch: cached launches stay out of a plain ``wp.Tape`` only where no array needs
gradients, a plain tape still gets the springs' gradients right (checked against central finite
differences of the spring force), and ``recording`` names the tape it enters."""

import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.core.launch import cached_launch, recording, recording_tape
from warpsim.kernels import autodiff as KD
from warpsim.kernels import integrate as KI

CPU = "cpu"
K_SPRING, REST = 40.0, 0.5


def test_recording_names_its_tape_and_refuses_a_second():
    tape = wp.Tape()
    assert recording_tape() is None
    with recording(tape):
        assert recording_tape() is tape
        with pytest.raises(RuntimeError, match="already recording"):
            with recording(wp.Tape()):
                pass
    assert recording_tape() is None


def test_cached_launches_reach_a_plain_tape_when_an_array_needs_gradients():
    cache: dict = {}
    for requires_grad, recorded in ((False, 0), (True, 2)):
        time = wp.zeros(1, dtype=float, device=CPU, requires_grad=requires_grad)
        tape = wp.Tape()
        with tape:
            for _ in range(2):
                cached_launch(KI.advance_time, 1, (time, 0.25), CPU, cache)
        assert len(tape.launches) == recorded
        assert time.numpy()[0] == 0.5  # both launches ran either way


def _spring_force_loss(x):
    """|f_0|^2 + |f_1|^2 of one spring (no damping) in float64: the test's reference."""
    d = x[0] - x[1]
    length = np.linalg.norm(d)
    f0 = -K_SPRING * (length - REST) * d / length
    return 2.0 * float(f0 @ f0)


def test_a_plain_tape_differentiates_the_springs():
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0))
    b.add_particle((0.7, 0.2, -0.1))
    b.add_spring(0, 1, K_SPRING, 0.0, rest_length=REST)
    model = b.finalize(CPU)
    springs = ws.Springs()
    springs.bind(model)
    x0 = model.particle_q.numpy().astype(np.float64)
    q = wp.array(x0.astype(np.float32), dtype=wp.vec3, device=CPU, requires_grad=True)
    qd = wp.zeros(2, dtype=wp.vec3, device=CPU, requires_grad=True)
    f = wp.zeros(2, dtype=wp.vec3, device=CPU, requires_grad=True)
    zero = wp.zeros(2, dtype=wp.vec3, device=CPU)
    loss = wp.zeros(1, dtype=float, device=CPU, requires_grad=True)
    time = wp.zeros(1, dtype=float, device=CPU)
    tape = wp.Tape()
    with tape:
        springs.eval(q, qd, time, 0.0, f)
        wp.launch(KD.squared_distance, 2, inputs=[f, zero, 1.0, loss], device=CPU)
    tape.backward(loss)
    assert loss.numpy()[0] == pytest.approx(_spring_force_loss(x0), rel=1e-5)
    eps, expected = 1e-6, np.zeros_like(x0)
    for i in range(2):
        for a in range(3):
            up, down = x0.copy(), x0.copy()
            up[i, a] += eps
            down[i, a] -= eps
            expected[i, a] = (_spring_force_loss(up) - _spring_force_loss(down)) / (2.0 * eps)
    assert np.allclose(q.grad.numpy(), expected, rtol=1e-3, atol=1e-3 * np.abs(expected).max())
