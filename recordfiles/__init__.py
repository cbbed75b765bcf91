"""Record files, read and written: excitation x, the response(s), the sampling rate and the
operating conditions, as CSV, NPZ or MAT.

Below both the service and the simulator, so that one package holds the format: the reader
(:mod:`recordfiles.reader`, with :mod:`recordfiles.matfiles`) that uploads and the command line
go through, the writer (:mod:`recordfiles.writer`) the simulator uses, and the rules for the
names a file carries (:mod:`recordfiles.names`, :mod:`recordfiles.channels`,
:mod:`recordfiles.conditions`), which every other way into the service applies too. It imports
nothing of the project but ``models`` (for :class:`models.errors.InputError`).
"""
