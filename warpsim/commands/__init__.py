"""The ``warpsim`` commands that belong to no single domain: ``list`` (:mod:`.listing`), ``run``
(:mod:`.run`) and ``info`` (:mod:`.info`). The others live with their domain: ``view``
(``warpsim.viewer.command``), ``render`` / ``plot`` / ``export`` (``warpsim.render``), ``sweep`` /
``query`` (``warpsim.sweeps``), ``pick`` (``warpsim.browse.pick``). ``warpsim.cli`` only
dispatches: its ``COMMANDS`` table names every command's module, each defining
``add_parser(sub)`` and ``run(args, out, err)``; the options they share are public names of
:mod:`warpsim.cli_common`."""
