"""Physics of the interaction, computed from the 4D result: the body's and object's mass model,
filtered kinematics, Newton-Euler contact forces and joint torques, and the object's free flight
under gravity (GraviCap-style parabola fits, and gravity's direction from them when no floor is
seen). Pure functions on arrays/tensors in SI units, world frame; the `physics` stage composes them.
"""
