"""Geometry measured from the inputs: depth maps aligned to metric depth, scene flow lifted from frames."""
