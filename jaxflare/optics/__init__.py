"""jaxflare.optics."""
