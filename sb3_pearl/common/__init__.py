"""Code shared by the algorithms: buffers, context inference, evaluation, type aliases."""
