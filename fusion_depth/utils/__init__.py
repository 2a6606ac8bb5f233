"""The lowest layer: what every other part uses and that knows nothing of depth or training:
atomic file writes (:mod:`.atomic`), checkpoint files and JSON files read as data
(:mod:`.checkpoint_file`, :mod:`.json_file`),
config schemas (:mod:`.schema`), a value as typed on the command line (:mod:`.overrides`),
progress, tables and console noise."""
