"""Print, as JSON, the jobs of a config's report DAG whose params share a value's text (run by
tests/test_workflow.py in a subprocess: the Snakemake API keeps global state). Snakemake records
a job's params as the set of their values' texts, without names, so such params can change
unnoticed; `named` (workflow/rules/common.smk) guards a rule against it."""
import collections
import json
import sys
from pathlib import Path

import snakemake.api as api
from snakemake.settings.enums import Quietness
from snakemake.settings.types import (ConfigSettings, DAGSettings, OutputSettings,
                                      ResourceSettings, StorageSettings)

configs = [Path(c) for c in sys.argv[1:]]
with api.SnakemakeApi(OutputSettings(quiet={Quietness.ALL})) as sm:
    wf = sm.workflow(resource_settings=ResourceSettings(cores=1),
                     config_settings=ConfigSettings(configfiles=configs),
                     storage_settings=StorageSettings(), snakefile=Path("Snakefile"),
                     workdir=Path("."))
    dag_api = wf.dag(DAGSettings(targets={"report"}, forceall=True))
    dag_api.execute_workflow(executor="dryrun")
    dag = dag_api.workflow_api._workflow.dag
    found = {}
    for job in dag.jobs:
        names, texts = list(job.params.keys()), [repr(v) for v in job.params]
        shared = {t: [n for n, u in zip(names, texts) if u == t]
                  for t, k in collections.Counter(texts).items() if k > 1 and t != "None"}
        if shared:
            found[job.rule.name] = {"shared": shared, "named": "named" in names}
print("COLLISIONS " + json.dumps(found))
