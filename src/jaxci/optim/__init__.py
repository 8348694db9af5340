"""Stage 4 of the flow: the optimizers (Cohort Intelligence, gradient methods, Laplace, untangling) and their
helpers."""
