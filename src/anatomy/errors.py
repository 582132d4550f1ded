"""The one error this package raises for bad input: what is wrong, where, and what to do."""


class AnatomyError(ValueError):
    """A lumen surface, a wall or a centerline request that cannot be used, with the fix."""
