"""Scenes: the description (:mod:`.spec`), reading it, and building it into arrays, models,
motions, obstacles and contact (:mod:`.build`)."""
