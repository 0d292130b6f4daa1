"""The HTTP API: `app.api.app.create_app()` builds the FastAPI application; one router module per resource
(`app.api.routes`).

A namespace of modules: this file re-exports nothing, so that a module needed alone (the wire codecs that
`app.client` uses, `app.api.cli`) is imported without the application and its models. Other rooms import
from the defining module: `app.api.app.create_app`, `app.api.cli.add_parser`, `app.api.wire` (the msgpack
codecs).
"""
