"""jaxflare.render."""
