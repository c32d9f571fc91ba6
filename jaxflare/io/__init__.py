"""jaxflare.io."""
