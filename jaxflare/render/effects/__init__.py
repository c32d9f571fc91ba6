"""jaxflare.render.effects."""
