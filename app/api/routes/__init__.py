"""One router module per resource: a namespace of modules, each exporting its `router` to `app.api.app`."""
