from ._app.command import run

run()
