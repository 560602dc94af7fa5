"""The scripted expert: part-aware grasp and touch poses and a batched skill state machine in JAX."""
