"""The closed-loop scale-factor estimator and what it models of the lock-in's stream."""
