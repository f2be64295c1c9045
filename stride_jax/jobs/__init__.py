"""Jobs: the ``stride`` subcommands that are applications of the library rather than parts of it
(each a frozen config nesting the library's own, named presets, and ``run``). The library
imports none of them. Older subcommands still keep their job beside their library package
(``sim/collect.py``, ``train/job.py``, ``eval/table.py``, ``control/closed_loop.py`` ...)."""
