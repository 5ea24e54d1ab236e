"""mrchaos: robotic tangram assembly from silhouettes, learnt on chaos objects.

Importing it sets nothing: MuJoCo's OpenGL backend is chosen by :mod:`mrchaos.sim.opengl`
when a picture is first drawn, and a ``MUJOCO_GL`` set by the user is kept.
"""

__version__ = "0.1.0"
