"""The service layer shared by the HTTP API and the workers.

Settings, database and models, migrations, the artifact store, the queue interface
and the job runner. It imports ``core`` and nothing of the routers or ``worker/``:
routers → service → core and worker → service → core, with no way back.
"""
