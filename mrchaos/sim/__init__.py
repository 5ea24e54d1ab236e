"""Simulation: the MJCF scene, batched MuJoCo worlds, the UR5e (kinematics, robot, executor), MuJoCo rendering."""
