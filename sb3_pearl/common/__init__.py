"""The algorithms' building blocks: networks, soft actor-critic math, buffers, context inference, task helpers, the
adaptation API's type, persistence, seeding and argument checks. The evaluation protocol is ``sb3_pearl.evaluation``."""
