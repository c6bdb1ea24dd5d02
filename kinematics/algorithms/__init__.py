"""Free functions of (model, state): forward kinematics, inverse kinematics, loop closure, segment poses, functional joints."""
