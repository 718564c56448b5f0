"""`epc-offboard sim`: the bundled SITL(s) and the service as real processes, a scenario, a
report. One module per role, each importing only those before it:

* :mod:`.envelope` and :mod:`.logscan`: pure: the sane envelope of a flight and where a
  flight left it; every warning and error a process logged, counted by kind;
* :mod:`.scenario`: the scenarios (``config/scenarios/NAME.toml``);
* :mod:`.options`: ``SimOptions``, what one run was asked to do, read from the command line once;
* :mod:`.analysis`: pure: what a flight's files say it achieved (tracking on ground truth,
  constraint violations, library use, warnings, the envelope);
* :mod:`.report`: the report JSON, its table, target verdicts, the failures and exit code;
* :mod:`.orchestrate`: the SITL and service processes: started, watched, stopped; then
  analysed and reported;
* :mod:`.command`: the command line's entry (``--compare`` goes to
  :mod:`epc_offboard.tools.compare`).

Nothing is imported here, so importing one part loads only what it needs.
"""
