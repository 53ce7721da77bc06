"""The training loop: the Experiment and the parts it builds (learner, algorithms, callbacks, tasks, ...)."""
