"""jaxflare.scene."""
