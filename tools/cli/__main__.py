"""``python -m tools.cli``: the ``pfma`` command without the console script."""

try:
    from tools.cli import main
except KeyboardInterrupt:  # Ctrl-C while starting: no traceback (main() says nothing either)
    raise SystemExit(130) from None

raise SystemExit(main())
