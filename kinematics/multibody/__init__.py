"""The multibody model: bodies, coordinates, joints, scalar functions and couplers (immutable descriptions)."""
