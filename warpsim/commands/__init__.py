"""The ``warpsim`` commands that belong to no single domain: ``list`` (:mod:`.listing`), ``run``
(:mod:`.run`) and ``info`` (:mod:`.info`). The others live with their domain: ``view``
(``warpsim.viewer.command``), ``render`` / ``plot`` / ``export`` (``warpsim.render``), ``sweep`` /
``query`` (``warpsim.sweeps``), ``pick`` (``warpsim.browse.pick``). ``warpsim.cli`` only
dispatches: its ``COMMANDS`` table names every command's module, each defining
``add_parser(sub)`` and ``run(args, out, err)``; the options they share are public names of
:mod:`warpsim.cli_common`. :mod:`.corpus` is no command: the full-length corpus (every scene,
slider end, README run and blow-up) run through ``warpsim run``'s own code by
``benchmarks/check_scenes.py`` and ``tests/test_full_length.py``."""
