"""Euler's disk by `sympy.physics.mechanics.KanesMethod`, from its bodies, frames and
rolling condition, lambdified to NumPy: what a mechanician who derives the disk with
sympy integrates with SciPy, built without nhjax's mass matrix or constraint matrix. The
tests check `nhjax.examples.rolling_disk_3d` against it; `scaling.py` times SciPy's
DOP853 on it against nhjax."""

import functools

import numpy as np
import sympy as sm
import sympy.physics.mechanics as me


PARAMETERS = ("m", "r", "g", "J_axle", "J_diameter")


@functools.cache
def kanes_equations():
    """`f(q, u, parameters) -> (qdot, udot)` for the disk by Kane's method, lambdified to
    NumPy: q = (x, y, phi, theta, psi) as in the example, u = qdot, with u_x and u_y
    the dependent speeds of the two rolling constraints (the velocity of the disk's
    material point at the contact vanishes)."""
    q = me.dynamicsymbols("x y phi theta psi")
    u = me.dynamicsymbols("u_x u_y u_phi u_theta u_psi")
    x, y, phi, theta, psi = q
    m, r, g, j_axle, j_diameter = sm.symbols(PARAMETERS, positive=True)
    ground = me.ReferenceFrame("N")
    heading = ground.orientnew("Y", "Axis", [phi, ground.z])
    lean = heading.orientnew("L", "Axis", [theta, heading.x])
    body = lean.orientnew("R", "Axis", [psi, lean.y])
    lean.set_ang_vel(ground, u[2] * ground.z + u[3] * heading.x)
    body.set_ang_vel(ground, u[2] * ground.z + u[3] * heading.x + u[4] * lean.y)
    origin = me.Point("O")
    origin.set_vel(ground, 0)
    contact = origin.locatenew("C", x * ground.x + y * ground.y)
    contact.set_vel(ground, u[0] * ground.x + u[1] * ground.y)
    centre = contact.locatenew("D", r * lean.z)
    centre.set_vel(ground, contact.vel(ground) + lean.ang_vel_in(ground).cross(r * lean.z))
    disk = me.RigidBody("disk", centre, body, m, (me.inertia(lean, j_diameter, j_axle, j_diameter), centre))
    slip = centre.vel(ground) + body.ang_vel_in(ground).cross(-r * lean.z)
    kane = me.KanesMethod(
        ground,
        q_ind=q,
        u_ind=u[2:],
        u_dependent=u[:2],
        kd_eqs=[qi.diff() - ui for qi, ui in zip(q, u)],
        velocity_constraints=[slip.dot(ground.x), slip.dot(ground.y)],
    )
    kane.kanes_equations([disk], [(centre, -m * g * ground.z)])
    # The right-hand side orders u as (independent, dependent).
    order = [u[2], u[3], u[4], u[0], u[1]]
    rhs = sm.lambdify((q, order, (m, r, g, j_axle, j_diameter)), kane.rhs(), cse=True, modules="numpy")

    def field(q_values, u_values, parameters):
        ordered = [u_values[2], u_values[3], u_values[4], u_values[0], u_values[1]]
        derivative = np.asarray(rhs(q_values, ordered, parameters), dtype=float).ravel()
        qdot, udot_ordered = derivative[:5], derivative[5:]
        return qdot, udot_ordered[[3, 4, 0, 1, 2]]

    return field
