"""Composition roots: one class per process kind, each built on ``contextlib.ExitStack``.

Every process (the service, the controller, the recorder) is assembled here and only here;
the CLI verbs parse arguments and make one call, and ``sim/``, the benches and the tests use
the same classes (docs/architecture.md, "Where each process is assembled").
"""
