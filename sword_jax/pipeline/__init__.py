"""The orchestration above the library: a run set up from many parts (GRPO's inputs, simulators and
evaluations), resumable stages and what is made of their results (reports, comparisons, figures).

Functions take typed configs and return data; the simulators enter as arguments, never as imports
(``sim`` sits above this package). The entry points in ``train/`` parse a command line and call these.
"""
