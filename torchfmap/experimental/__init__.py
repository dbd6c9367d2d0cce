"""Experiments kept available and tested outside the core API: what was measured and did not
earn a place in the core (see each module's docstring for its measurement)."""
