"""The params of every job of a config's report DAG, as Snakemake records them (the set of their
values' texts), printed as JSON for tests/test_workflow.py, which runs this in a subprocess (the
Snakemake API keeps global state). No job runs.

    python tests/job_params.py collisions CONFIG...  jobs whose params share a value's text
    python tests/job_params.py texts CONFIG...       each job's sorted params texts
    python tests/job_params.py resources CONFIG...   per rule, its jobs' runtime and gpu
                                                     (the largest; '<TBD>' until inputs exist)

Snakemake records a job's params without their names, so params that share a value can change
unnoticed; `named` (workflow/rules/common.smk) guards a rule against it."""
import collections
import json
import sys
from pathlib import Path

import snakemake.api as api
from snakemake.settings.enums import Quietness
from snakemake.settings.types import (ConfigSettings, DAGSettings, OutputSettings,
                                      ResourceSettings, StorageSettings)

mode, configs = sys.argv[1], [Path(c) for c in sys.argv[2:]]
with api.SnakemakeApi(OutputSettings(quiet={Quietness.ALL})) as sm:
    wf = sm.workflow(resource_settings=ResourceSettings(cores=1),
                     config_settings=ConfigSettings(configfiles=configs),
                     storage_settings=StorageSettings(), snakefile=Path("Snakefile"),
                     workdir=Path("."))
    dag_api = wf.dag(DAGSettings(targets={"report"}, forceall=True))
    dag_api.execute_workflow(executor="dryrun")
    try:  # Snakemake's own DAG: no public API lists a job's params
        dag = dag_api.workflow_api._workflow.dag
    except AttributeError as e:
        print(f"UNAVAILABLE this Snakemake keeps its DAG elsewhere: {e}")
        sys.exit(3)
    found = {}
    for job in dag.jobs:
        if mode == "resources":  # what Slurm would be asked for (README "Running on Slurm")
            got = found.setdefault(job.rule.name, {})
            for key in ("runtime", "gpu"):
                v = job.resources.get(key)
                v = v if isinstance(v, int) else str(v)
                old = got.get(key)
                got[key] = v if old is None or (isinstance(v, int) and isinstance(old, int)
                                                and v > old) else old
            continue
        names, texts = list(job.params.keys()), [repr(v) for v in job.params]
        if mode == "texts":
            if job.rule.name != "report":  # its params are the whole config, as written
                found[f"{job.rule.name} {sorted(job.wildcards.items())}"] = sorted(texts)
            continue
        shared = {t: [n for n, u in zip(names, texts) if u == t]
                  for t, k in collections.Counter(texts).items() if k > 1 and t != "None"}
        if shared:
            found[job.rule.name] = {"shared": shared, "named": "named" in names}
print("RESULT " + json.dumps(found))
