"""Tasks: chaos objects, the target sampler and the task presets (tangram, cutlery, soda) with their goals."""
