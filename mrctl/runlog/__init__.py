"""What a run log is: its columns (:mod:`~mrctl.runlog.format`) and the
tracking figures computed from one (:mod:`~mrctl.runlog.metrics`)."""
