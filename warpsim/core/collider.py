"""The collider interface the Simulator steps; the shapes live in ``warpsim.bodies.colliders``."""


class Collider:
    """Base class: ``bind(model)`` once, then ``apply(model, state, q_prev, dt)`` after every
    integration step (``q_prev``: positions at the start of the step, for continuous detection)."""

    def bind(self, model) -> None:
        self.model = model

    def apply(self, model, state, q_prev, dt: float) -> None:
        raise NotImplementedError
