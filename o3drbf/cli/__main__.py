from o3drbf.cli.commands import run

run()
