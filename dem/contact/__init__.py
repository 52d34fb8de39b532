"""Contact laws (normal + tangential, rolling resistance) and their registry."""
from .registry import CONTACT_MODELS, ROLLING_MODELS, DAMPING_MODELS, TANGENTIAL_MODELS  # noqa: F401
