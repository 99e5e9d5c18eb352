"""The ``diff4splat`` commands, one module each (``generate``, ``reconstruct``, ``export-onnx``, ``render``, ``view``):
each owns its flags and registers them with ``register(subparsers)``, whose parser's defaults hold ``func(args) ->
int``, the convention of the ``diff4splat.commands`` entry points (``training``'s ``evaluate`` and ``fit``);
:mod:`diff4splat.cli` only dispatches."""
