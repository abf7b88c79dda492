"""The tick: one control period's good path, compiled ahead of time.

``controller.py`` (one tick: sample, observer, laws, clamp and slew, the log
row) and ``safety.py`` (the supervisor's per-tick rules, configured by
``safety_config.py``) are plain type-hinted Python that mypyc compiles at
install (mrctl/build.py lists the modules; docs/design.md, "The compiled
core"). The daemon's loop and ``mrctl simulate`` both run this code, so an
offline run and a live one tick the same way.
"""
