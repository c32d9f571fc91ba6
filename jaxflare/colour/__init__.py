"""jaxflare.colour."""
