"""Stage 4, capability: capability maps, their store, RASSCMAP setup planning and scale-out."""
