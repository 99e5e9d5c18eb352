"""Building a scene from the networks' outputs and the photograph: the photo layer, the assembly of the
generated layers, settling and pruning, and motion read from frames."""
