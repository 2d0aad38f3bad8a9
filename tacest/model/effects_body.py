"""Effects on the body: angular_damping, linear_drag and com_offset (2-D and 3-D)."""

from __future__ import annotations

import casadi as ca

from tacest.model.effect import Effect, EffectParameter


class AngularDamping(Effect):
    """A torque -c·ω against the spin, c in units of m0·L² per second (N·m·s)."""

    name = "angular_damping"
    dims = (2, 3)
    doc = "torque against spin: -c·ω"

    def parameters(self, K, dim):
        return (EffectParameter("c", 0.0, 5.0, 0.0, 200.0, unit="N·m·s", per_unit=lambda sc: sc.m0 * sc.L * sc.L,
                                doc="damping coefficient"),)

    def body_impulse_2d(self, ctx):
        c_ang = ctx.u[self.name]["c"] * ctx.m0 * ctx.L * ctx.L  # N·m·s
        return ca.vertcat(0, 0, -c_ang * ctx.v[2] * ctx.dt)

    def body_impulse_3d(self, ctx):
        # isotropic: -c·ω is the same in the body and the world frame (as the simulator's
        # damping of the free joint)
        c_ang = ctx.u[self.name]["c"] * ctx.m0 * ctx.L * ctx.L  # N·m·s
        return ca.SX.zeros(3), -c_ang * ctx.w * ctx.dt


class LinearDrag(Effect):
    """A force -b·v on the centre of mass over the interval (implicit), b in units of m0
    per second (N·s/m)."""

    name = "linear_drag"
    dims = (2, 3)
    doc = "force against velocity: -b·v"

    def parameters(self, K, dim):
        return (EffectParameter("b", 0.0, 5.0, 0.0, 200.0, unit="N·s/m", per_unit=lambda sc: sc.m0,
                                doc="drag coefficient"),)

    def body_impulse_2d(self, ctx):
        b = ctx.u[self.name]["b"] * ctx.m0  # N·s/m
        return ca.vertcat(-b * ctx.v[0] * ctx.dt, -b * ctx.v[1] * ctx.dt, 0)

    def body_impulse_3d(self, ctx):
        b = ctx.u[self.name]["b"] * ctx.m0  # N·s/m
        return -b * ctx.v * ctx.dt, ca.SX.zeros(3)


class ComOffset(Effect):
    """The centre of mass away from the shape's centroid by (dx, dy[, dz]) in body axes,
    units of L: the body frame's origin is the COM, so the vertices move by -(dx, dy[, dz]);
    the inertia about the COM stays the shape's about its centroid (as simulated)."""

    name = "com_offset"
    dims = (2, 3)
    doc = "centre of mass away from the shape's centroid"

    def parameters(self, K, dim):
        return tuple(EffectParameter(f"d{a}", 0.0, 0.3, -0.5, 0.5, unit="m", per_unit=lambda sc: sc.L,
                                     doc=f"COM offset along the body {a} axis") for a in "xyz"[:dim])

    def body_vertices_2d(self, V, u, L):
        d = ca.horzcat(u["dx"], u["dy"]) * L
        return V - ca.repmat(d, V.shape[0], 1)

    def com_shift_3d(self, u, L):
        return ca.vertcat(u["dx"], u["dy"], u["dz"]) * L
