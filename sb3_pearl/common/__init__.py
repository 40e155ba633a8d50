"""Code shared by the algorithms: networks, buffers, context inference, task helpers, the adaptation protocol,
the meta-test and its statistics."""
