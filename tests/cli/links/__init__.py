"""Links that drop or lag during a run: the link guard, its resume and the soak runs."""
