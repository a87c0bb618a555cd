"""Helpers the tests share: the in-process team harness (`team`), the reference model of docs/model.md
(`reference_model`), learner settings (`learning`) and scenario events (`events`). Fixtures stay in conftest.py;
a test module imports helpers from here, never from another test module or from a conftest."""
