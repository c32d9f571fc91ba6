"""jaxflare.polynomial."""
