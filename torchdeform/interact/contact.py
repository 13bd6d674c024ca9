"""Contact between tools and tissue: projection after the step, or a smooth penalty force.

Both are contact responses a :class:`~torchdeform.sim.model.Model` takes through
``Model(..., interactions=[...])``; the model knows them only by two methods, so the mass-spring core
does not import this package:

* ``project(model, x, v, t, dt, *, readings=None) -> (x, v)``, called by every integrator at the end of
  a step (after dragged nodes are put on their path), inside the compiled step too; it adds what
  it measured (forces on the tools, :mod:`~torchdeform.interact.reactions`) to the dict
  ``readings``, which the step returns as ``State.readings``;
* ``force(model, x, v, t) -> (B, 3, ...) | None``, added to the model's forces.

:class:`ProjectionContact` (Punak eqs. 4-3..4-5): a free node that penetrates a tool
(``d < 0``) is moved to the surface, ``x <- x - d n``; its velocity relative to the tool loses
its approaching normal part (inelastic), and with Coulomb friction ``mu`` the tangential part
shrinks by ``mu`` times the removed normal speed (to zero at most: sticking), and the slip that
the step made with the removed tangential speed (``dt`` times it: exact for symplectic Euler,
``x1 = x0 + dt v1``) is taken back. A node resting on a floor tilted by ``theta`` therefore stays
put when ``tan(theta) <= mu`` and slides with acceleration ``g (sin theta - mu cos theta)``
otherwise. With ``direction="motion"`` the node goes out along the tool's direction of motion
instead (Radetzky), and ``hold=True`` keeps touched nodes on the tool until they pull away.

:class:`PenaltyContact`: the force ``k max(-d, 0) n - c min(v_rel . n, 0) n`` on penetrating
nodes, smooth in the node positions, the stiffness and the tool's position away from contact
onset (``d = 0``), so it can be learned through.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact import HalfSpace, ProjectionContact, Tool
    >>> grid = td.Grid((2, 2, 2), spacing=0.01)
    >>> floor = Tool(HalfSpace(normal=(1.0, 0.0, 0.0)), position=(-0.001, 0.0, 0.0))   # 1 mm below the body
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
from .grasp import Attachment
from .reactions import report, report_momentum
from .tools import Tool, _field, length

__all__ = ["ProjectionContact", "PenaltyContact"]


def _tools(tools) -> list:
    tools = [tools] if isinstance(tools, Tool) else list(tools)
    if not tools or not all(isinstance(t, Tool) for t in tools):
        raise ConfigError("contact.tools", "one Tool or a list of Tools", got=tools)
    return tools


def _number(value, key, expected, low=0.0):
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value) or value < low:
        raise ConfigError(key, expected, got=value)
    return float(value)


#: projection directions: the surface normal (Punak) or the tool's direction of motion (Radetzky)
DIRECTIONS = ("normal", "motion")


class ProjectionContact:
    """Penetrating free nodes projected onto the tools' surfaces after every step.

    Args:
        tools: a :class:`~torchdeform.interact.tools.Tool` or a list of them (also static
            obstacles: a floor is a tool with a :class:`HalfSpace` shape and a fixed position).
        friction: Coulomb coefficient ``mu >= 0`` (0: frictionless).
        direction: ``"normal"`` (the nearest surface point, Punak) or ``"motion"`` (along the
            tool's direction of motion, Radetzky; the normal where the tool stands still or the
            node is beside it: where the normal and the motion are less than 60 degrees apart).
        hold: Radetzky's remedy against jitter: a node the tool touched stays fixed to the tool
            until its velocity relative to the tool points away from it (its force pulls it off).
            Eager step only.
        haptic_gain: report Punak's haptic force ``<name>.haptic = -gain * mean(Delta_i)`` (N), the
            mean push-out ``Delta_i`` of the nodes projected this step, with ``gain`` in N/m
            (None: not reported).

    Reports ``<name>.force``, ``<name>.torque`` and ``<name>.contacts`` per tool every step (see
    :mod:`~torchdeform.interact.reactions`).

    Examples:
        >>> import torch
        >>> from torchdeform.interact import Sphere, Tool
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((1, 1, 1), spacing=1.0), stiffness=1.0, mass=1.0, dtype=torch.float64)
        >>> c = ProjectionContact(Tool(Sphere(0.5), position=(0.3, 0.0, 0.0)))
        >>> x, v = c.project(model, torch.zeros(1, 3, 1, 1, 1, dtype=torch.float64),
        ...                  torch.ones(1, 3, 1, 1, 1, dtype=torch.float64), 0.0, 0.01)
        >>> x.flatten().tolist(), v.flatten().tolist()       # pushed out along -D; the inward speed is gone
        ([-0.2, 0.0, 0.0], [0.0, 1.0, 1.0])
    """

    def __init__(
        self,
        tools,
        *,
        friction: float = 0.0,
        direction: str = "normal",
        hold: bool = False,
        haptic_gain: float | None = None,
    ):
        self.tools = _tools(tools)
        self.friction = _number(friction, "contact.friction", "a Coulomb coefficient >= 0")
        if direction not in DIRECTIONS:
            raise ConfigError("contact.direction", " or ".join(DIRECTIONS), got=direction)
        self.direction, self.hold = direction, bool(hold)
        self.haptic_gain = (
            None if haptic_gain is None else _number(haptic_gain, "contact.haptic_gain", "a gain >= 0 (N/m)")
        )
        self._held = [Attachment() for _ in self.tools] if self.hold else None

    @property
    def eager_only(self) -> bool:
        """With ``hold`` the held nodes live in Python between steps: a compiled step runs eagerly."""
        return self.hold

    def force(self, model, x, v, t):
        """Projection adds no force."""
        return None

    def _push_out(self, tool, x, d, n, t, inside):
        """Penetrating nodes onto the surface: along the normal, or along the tool's motion."""
        if self.direction == "normal":
            return torch.where(inside, x - d * n, x)
        u = _field(tool.velocity(t), x)
        u = u / length(u).clamp_min(torch.finfo(x.dtype).tiny)
        ahead = inside & ((n * u).sum(1, keepdim=True) > 0.5)
        s = torch.zeros_like(d)
        for _ in range(4):  # Newton on sdf(x + s u) = 0 along the motion
            ds, ns = tool.sdf(x + s * u, t)
            s = s - ds / (ns * u).sum(1, keepdim=True).clamp_min(0.5)
        y = x + s * u
        ds, ns = tool.sdf(y, t)
        y = y - ds.clamp_max(0) * ns  # what the ray left inside goes along the normal
        return torch.where(ahead, y, torch.where(inside, x - d * n, x))

    def project(self, model, x, v, t, dt, *, readings=None):
        """Nodes inside a tool moved to its surface at time ``t``, velocities corrected.

        Eager steps on the CPU without a gradient respond on the nodes some tool reaches alone
        (gathered, then written back): the same arithmetic per node, a few instead of every node.

        Args:
            model: the model (its ``free`` mask: fixed and dragged nodes are not moved).
            x: positions ``(B, 3, ...)`` at the end of the step.
            v: velocities ``(B, 3, ...)``.
            t: the time at the end of the step (a float or a 0-d tensor).
            dt: the step (s): the slip that friction takes back is ``dt`` times the removed speed.
            readings: the step's readings dict (forces are added to it), or None.
        """
        free, mass = model.free, model.mass
        for k, tool in enumerate(self.tools):
            # each tool reads the state many times: under torch.compile it is stored once first,
            # or every read would recompute the step and the tools before (compile time explodes)
            x, v = model.keep(x), model.keep(v)
            if self.hold:
                if torch.is_tensor(t):
                    raise ConfigError(
                        "contact.hold", "the eager step (held nodes are kept in Python)", got="a compiled step"
                    )
                att = self._held[k]
                x0, v0 = x, v
                if att.mask is not None:  # release the held nodes whose motion leaves the tool
                    _, n = tool.sdf(x, t)
                    leaving = ((v - tool.point_velocity(x, t)) * n).sum(1, keepdim=True) > 0
                    att.release(which=leaving)
                    x, v = att.follow(tool, x, v, t)
                x, v = self._respond(k, tool, x, v, t, dt, free, mass, readings, held=att.mask, x0=x0, v0=v0)
            elif _gathered(x, v, t):
                x, v = self._respond_reached(k, tool, x, v, t, dt, free, mass, readings)
            else:
                x, v = self._respond(k, tool, x, v, t, dt, free, mass, readings)
        return x, v

    def _respond_reached(self, k, tool, x, v, t, dt, free, mass, readings):
        """:meth:`_respond` on the nodes tool ``k`` reaches in any batch entry, gathered and written back."""
        d, _ = tool.sdf(x, t)
        reach = d < 0 if free is None else (d < 0) & (free > 0)
        idx = reach.flatten(2).any(1).any(0).nonzero()[:, 0]
        shape = x.shape[2:]
        xs, vs = self._respond(
            k,
            tool,
            _take(x, idx, shape),
            _take(v, idx, shape),
            t,
            dt,
            None if free is None else _take(free, idx, shape),
            _take(mass, idx, shape),
            readings,
        )
        return x.flatten(2).index_copy(2, idx, xs).view_as(x), v.flatten(2).index_copy(2, idx, vs).view_as(v)

    def _respond(self, k, tool, x, v, t, dt, free, mass, readings, *, held=None, x0=None, v0=None):
        """Tool ``k``'s response on nodes ``x``, ``v`` ``(B, 3, ...)`` (all, or those gathered): ``(x, v)``.

        ``x0``, ``v0``: the state before a held contact's nodes followed the tool (default ``x``, ``v``).
        """
        x0 = x if x0 is None else x0
        v0 = v if v0 is None else v0
        d, n = tool.sdf(x, t)
        inside = d < 0
        if free is not None:
            inside = inside & (free > 0)
        if held is not None:
            inside = inside & ~held
        x = self._push_out(tool, x, d, n, t, inside)
        if self.direction != "normal":
            _, n = tool.sdf(x, t)
        vt = tool.point_velocity(x, t)
        vr = v - vt
        vn = (vr * n).sum(1, keepdim=True)
        hit = inside & (vn < 0)
        tangential = vr - vn * n
        if self.friction > 0:
            speed = length(tangential)
            keep = (1 - self.friction * (-vn) / speed.clamp_min(torch.finfo(v.dtype).tiny)).clamp_min(0)
            # the step moved the node by dt * v along the surface (x1 = x0 + dt v1): friction
            # takes back the part of that slip it removes from the velocity
            x = torch.where(hit, x - dt * (1 - keep) * tangential, x)
            tangential = tangential * keep
        v = torch.where(hit, tangential + vt, v)
        if self.hold:
            self._held[k].attach(tool, inside, x, t)
        if readings is not None:
            c, _ = tool.frame(t, x)
            report_momentum(readings, tool.name, mass, v - v0, x, c, dt)
            touched = inside if held is None else inside | held
            report(readings, tool.name, "contacts", touched.flatten(1).sum(1).to(x.dtype))
            if self.haptic_gain is not None:
                n_in = inside.flatten(2).sum(2).to(x.dtype)  # (B, 1)
                push = torch.where(inside, x - x0, torch.zeros_like(x)).flatten(2).sum(2)
                report(readings, tool.name, "haptic", -self.haptic_gain * push / n_in.clamp_min(1))
        return x, v


def _take(field: torch.Tensor, idx: torch.Tensor, shape) -> torch.Tensor:
    """The nodes ``idx`` of a node field ``(B|1, C, ...)`` (broadcast to the nodes ``shape``): ``(B|1, C, K)``."""
    return field.expand(*field.shape[:2], *shape).flatten(2).index_select(2, idx)


def _gathered(x: torch.Tensor, v: torch.Tensor, t) -> bool:
    """Whether a response may run on the touched nodes alone: an eager CPU step without a gradient.

    (Finding them reads a count on the host: free on the CPU, a wait on an accelerator; a compiled
    graph keeps dense shapes; autograd keeps the whole fields.)
    """
    return (
        x.device.type == "cpu"
        and not torch.is_tensor(t)
        and not torch.compiler.is_compiling()
        and not (torch.is_grad_enabled() and (x.requires_grad or v.requires_grad))
    )


class PenaltyContact:
    """A smooth penalty force pushing penetrating nodes out of the tools.

    Args:
        tools: a :class:`~torchdeform.interact.tools.Tool` or a list of them.
        stiffness: N/m per node and metre of penetration (a number or a tensor, may require grad).
        damping: N s/m on the approaching normal speed (0: none).

    Examples:
        >>> import torch
        >>> from torchdeform.interact import HalfSpace, Tool
        >>> c = PenaltyContact(Tool(HalfSpace(normal=(1.0, 0.0, 0.0)), position=(0.0, 0.0, 0.0)), stiffness=100.0)
        >>> x = torch.tensor([[[-0.01], [0.0], [0.0]]], dtype=torch.float64)     # 1 cm below the floor
        >>> c.force(None, x, torch.zeros_like(x), 0.0).flatten().tolist()
        [1.0, 0.0, 0.0]
    """

    def __init__(self, tools, stiffness, *, damping: float = 0.0):
        self.tools = _tools(tools)
        k = stiffness
        if not torch.is_tensor(k) and (not isinstance(k, (int, float)) or not math.isfinite(k) or k <= 0):
            raise ConfigError("contact.stiffness", "a positive number (N/m)", got=stiffness)
        self.stiffness, self.damping = stiffness, _number(damping, "contact.damping", "a number >= 0 (N s/m)")

    def force(self, model, x, v, t):
        """Penalty forces ``(B, 3, ...)`` on the nodes at positions ``x``, velocities ``v``, time ``t``.

        Args:
            model: the model (unused: forces on constrained nodes are discarded by the integrators).
            x: positions ``(B, 3, ...)``.
            v: velocities ``(B, 3, ...)``.
            t: time (s), a float or a 0-d tensor.
        """
        total = None
        for f, _ in self._forces(x, v, t):
            total = f if total is None else total + f
        return total

    def _forces(self, x, v, t):
        """``(force field, penetrating mask)`` of each tool."""
        for tool in self.tools:
            d, n = tool.sdf(x, t)
            depth = (-d).clamp_min(0)
            f = self.stiffness * depth * n
            if self.damping > 0:
                vn = ((v - tool.point_velocity(x, t)) * n).sum(1, keepdim=True)
                f = f - self.damping * vn.clamp_max(0) * (depth > 0) * n
            yield f, d < 0

    def project(self, model, x, v, t, dt, *, readings=None):
        """Positions unchanged; reports each tool's force and torque, the penalty at the end of the step."""
        if readings is not None:
            for tool, (f, inside) in zip(self.tools, self._forces(x, v, t)):
                c, _ = tool.frame(t, x)
                report(readings, tool.name, "force", -f.flatten(2).sum(2))
                report(readings, tool.name, "torque", -torch.cross(x - c, f, dim=1).flatten(2).sum(2))
                report(readings, tool.name, "contacts", inside.flatten(1).sum(1).to(x.dtype))
        return x, v
