"""Former name of `rendering` (the local models), kept so that `haptic_fmu.local_model` imports work."""
from .rendering import LOCAL_POLICIES, LocalModel, LocalModelError  # noqa: F401
