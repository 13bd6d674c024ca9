"""Contact between tools and tissue: projection after the step, or a smooth penalty force.

Both are contact responses a :class:`~torchdeform.sim.model.Model` takes through
``Model(..., interactions=[...])``; the model knows them only by two methods, so the mass-spring core
does not import this package:

* ``project(model, x, v, t, dt) -> (x, v)``, called by every integrator at the end of a step
  (after dragged nodes are put on their path), inside the compiled step too;
* ``force(model, x, v, t) -> (B, 3, ...) | None``, added to the model's forces.

:class:`ProjectionContact` (Punak eqs. 4-3..4-5): a free node that penetrates a tool
(``d < 0``) is moved to the surface, ``x <- x - d n``; its velocity relative to the tool loses
its approaching normal part (inelastic), and with Coulomb friction ``mu`` the tangential part
shrinks by ``mu`` times the removed normal speed (to zero at most: sticking), and the slip that
the step made with the removed tangential speed (``dt`` times it: exact for symplectic Euler,
``x1 = x0 + dt v1``) is taken back. A node resting on a floor tilted by ``theta`` therefore stays
put when ``tan(theta) <= mu`` and slides with acceleration ``g (sin theta - mu cos theta)``
otherwise.

:class:`PenaltyContact`: the force ``k max(-d, 0) n - c min(v_rel . n, 0) n`` on penetrating
nodes, smooth in the node positions, the stiffness and the tool's position away from contact
onset (``d = 0``), so it can be learned through.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact import HalfSpace, ProjectionContact, Tool
    >>> grid = td.Grid((2, 2, 2), spacing=0.01)
    >>> floor = Tool(HalfSpace((1.0, 0.0, 0.0)), position=(-0.001, 0.0, 0.0))   # 1 mm below the body
    >>> model = td.Model(grid, stiffness=10.0, mass=1e-3, gravity=(-9.81, 0, 0),
    ...                  interactions=[ProjectionContact([floor])], dtype=torch.float64)
    >>> state, _ = td.simulate(model, model.rest_state(), dt=1e-3, steps=300)
    >>> bool(state.x[:, 0].min() >= -0.001 - 1e-12)                 # nothing sinks through the floor
    True
"""
from __future__ import annotations

import math

import torch

from ..errors import ConfigError
from .tools import Tool

__all__ = ["ProjectionContact", "PenaltyContact"]


def _tools(tools) -> list:
    tools = [tools] if isinstance(tools, Tool) else list(tools)
    if not tools or not all(isinstance(t, Tool) for t in tools):
        raise ConfigError("contact.tools", "one Tool or a list of Tools", tools)
    return tools


def _tool_velocity(tool: Tool, t, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(tool.velocity(t), dtype=like.dtype, device=like.device).view(1, 3, *[1] * (like.dim() - 2))


class ProjectionContact:
    """Penetrating free nodes projected onto the tools' surfaces after every step.

    Args:
        tools: a :class:`~torchdeform.interact.tools.Tool` or a list of them (also static
            obstacles: a floor is a tool with a :class:`HalfSpace` shape and a fixed position).
        friction: Coulomb coefficient ``mu >= 0`` (0: frictionless).

    Examples:
        >>> import torch
        >>> from torchdeform.interact import Sphere, Tool
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((1, 1, 1), 1.0), stiffness=1.0, mass=1.0, dtype=torch.float64)
        >>> c = ProjectionContact(Tool(Sphere(0.5), position=(0.3, 0.0, 0.0)))
        >>> x, v = c.project(model, torch.zeros(1, 3, 1, 1, 1, dtype=torch.float64),
        ...                  torch.ones(1, 3, 1, 1, 1, dtype=torch.float64), 0.0, 0.01)
        >>> x.flatten().tolist(), v.flatten().tolist()       # pushed out along -D; the inward speed is gone
        ([-0.2, 0.0, 0.0], [0.0, 1.0, 1.0])
    """

    def __init__(self, tools, friction: float = 0.0):
        self.tools = _tools(tools)
        if not isinstance(friction, (int, float)) or not math.isfinite(friction) or friction < 0:
            raise ConfigError("contact.friction", "a Coulomb coefficient >= 0", friction)
        self.friction = float(friction)

    def force(self, model, x, v, t):
        """Projection adds no force."""
        return None

    def project(self, model, x, v, t, dt):
        """Nodes inside a tool moved to its surface at time ``t``, velocities corrected.

        Args:
            model: the model (its ``free`` mask: fixed and dragged nodes are not moved).
            x: positions ``(B, 3, ...)`` at the end of the step.
            v: velocities ``(B, 3, ...)``.
            t: the time at the end of the step (a float or a 0-d tensor).
            dt: the step (s): the slip that friction takes back is ``dt`` times the removed speed.
        """
        free = model.free
        for tool in self.tools:
            # each tool reads the state many times: under torch.compile it is stored once first,
            # or every read would recompute the step and the tools before (compile time explodes)
            x, v = model.keep(x), model.keep(v)
            d, n = tool.sdf(x, t)
            inside = d < 0
            if free is not None:
                inside = inside & (free > 0)
            x = torch.where(inside, x - d * n, x)
            vt = _tool_velocity(tool, t, v)
            vr = v - vt
            vn = (vr * n).sum(1, keepdim=True)
            hit = inside & (vn < 0)
            tangential = vr - vn * n
            if self.friction > 0:
                speed = tangential.norm(dim=1, keepdim=True)
                keep = (1 - self.friction * (-vn) / speed.clamp_min(torch.finfo(v.dtype).tiny)).clamp_min(0)
                # the step moved the node by dt * v along the surface (x1 = x0 + dt v1): friction
                # takes back the part of that slip it removes from the velocity
                x = torch.where(hit, x - dt * (1 - keep) * tangential, x)
                tangential = tangential * keep
            v = torch.where(hit, tangential + vt, v)
        return x, v


class PenaltyContact:
    """A smooth penalty force pushing penetrating nodes out of the tools.

    Args:
        tools: a :class:`~torchdeform.interact.tools.Tool` or a list of them.
        stiffness: N/m per node and metre of penetration (a number or a tensor, may require grad).
        damping: N s/m on the approaching normal speed (0: none).

    Examples:
        >>> import torch
        >>> from torchdeform.interact import HalfSpace, Tool
        >>> c = PenaltyContact(Tool(HalfSpace((1.0, 0.0, 0.0)), position=(0.0, 0.0, 0.0)), stiffness=100.0)
        >>> x = torch.tensor([[[-0.01], [0.0], [0.0]]], dtype=torch.float64)     # 1 cm below the floor
        >>> c.force(None, x, torch.zeros_like(x), 0.0).flatten().tolist()
        [1.0, 0.0, 0.0]
    """

    def __init__(self, tools, stiffness, damping: float = 0.0):
        self.tools = _tools(tools)
        k = stiffness
        if not torch.is_tensor(k) and (not isinstance(k, (int, float)) or not math.isfinite(k) or k <= 0):
            raise ConfigError("contact.stiffness", "a positive number (N/m)", stiffness)
        if not isinstance(damping, (int, float)) or not math.isfinite(damping) or damping < 0:
            raise ConfigError("contact.damping", "a number >= 0 (N s/m)", damping)
        self.stiffness, self.damping = stiffness, float(damping)

    def force(self, model, x, v, t):
        """Penalty forces ``(B, 3, ...)`` on the nodes at positions ``x``, velocities ``v``, time ``t``.

        Args:
            model: the model (unused: forces on constrained nodes are discarded by the integrators).
            x: positions ``(B, 3, ...)``.
            v: velocities ``(B, 3, ...)``.
            t: time (s), a float or a 0-d tensor.
        """
        total = None
        for tool in self.tools:
            d, n = tool.sdf(x, t)
            depth = (-d).clamp_min(0)
            f = self.stiffness * depth * n
            if self.damping > 0:
                vn = ((v - _tool_velocity(tool, t, v)) * n).sum(1, keepdim=True)
                f = f - self.damping * vn.clamp_max(0) * (depth > 0) * n
            total = f if total is None else total + f
        return total

    def project(self, model, x, v, t, dt):
        """A penalty changes nothing after the step."""
        return x, v
