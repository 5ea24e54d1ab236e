"""mrchaos: robotic tangram assembly from silhouettes, learnt on chaos objects."""

__version__ = "0.1.0"
