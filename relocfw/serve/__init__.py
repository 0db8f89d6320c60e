"""relocfw serve: an HTTP relocalization service (`relocfw task=serve serve.model=FILE`,
or `relocfw-serve FILE`; both in relocfw.app.tasks.serve, where the config is read).

One process holds the model in memory and answers `POST /v1/localize` (an encoded image
in, a pose with its trust and timings out), `GET /v1/health` and `GET /v1/model`.
The parts, one per module:

    settings   the serve.* options, checked (ServeSettings)
    images     the request body: content type, size, PNG / JPEG header, decoding
    fields     the query fields: intrinsics and frame name
    auth       the optional bearer token (serve.token_file)
    workers    where queries run: one thread, or one process per worker
    queue      the bounded queue in front of the workers (serve.max_pending)
    body_budget  the bytes of bodies still arriving, bounded
    answers    a Localization and the model as JSON
    app        the FastAPI application over all of them
    guard      around the application: refusals counted, requests cut off by a stop
    connections  below it: header timeout, connection caps, open files
    service    loading, serving, draining on SIGTERM and Ctrl-C

FastAPI, Starlette and uvicorn are imported by `app`, `guard`, `connections` and
`service` only: `pip install "relocfw[serve]"`.
"""
