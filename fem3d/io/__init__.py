"""Files: what every reader and writer shares (:mod:`.files`: atomic writes, input checks, safe
reads, temp cleanup), the run folder (:mod:`.rundir`), frames (:mod:`.frames`), the energy log
(:mod:`.energy`), pictures (:mod:`.preview`), checkpoints (:mod:`.checkpoint`) and datasets
(:mod:`.dataset`)."""
