"""Plate fitting for jaxflare: recover coating colours and lens-dirt attenuation from reference
flare images (built on the renderer; see the project's issues for the plan)."""
