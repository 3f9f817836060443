"""Renderers: the batched metric sphere (`sphere`), Mitsuba 3 figures (`mitsuba_bsdf`, `scenes`)
and image grids (`gallery`)."""
