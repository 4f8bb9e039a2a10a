"""The maths of learning: returns and advantages, losses, optimisers, networks, normalisation,
rollout and replay storage, and the hyperparameters shared by algorithm families. Nothing here
steps an env or writes a file."""
