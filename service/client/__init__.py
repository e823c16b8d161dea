"""A small Python client of the HTTP API (docs/design.md 3.5): what a studio's script does with the
service. Torch-free; only httpx.

    c = Client("http://127.0.0.1:8000", api_key)
    cap = c.create_capture("capture/")             # manifest: path, size, sha256 per file
    c.upload_capture(cap["id"], "capture/")        # tus, resumable, missing files only
    c.commit(cap["id"])
    job = c.submit(cap["id"], {"preset": "fast"})
    job = c.wait(job["id"], on_event=print)        # server-sent events, reconnecting
    bars = JobBars()                               # or: a bar for the job, one per running
    c.wait(job["id"], on_event=bars.on_event)      # part of a sequence run as parts
    c.download_all(job["id"], "results/")          # Range-resumed, SHA-256 checked
    env = c.upload_envmap("studio.exr")            # an environment map asset
    render = c.render(job["id"], env["id"], orbit=24)
    render = c.wait(render["id"])                  # a relight job, followed the same way
    c.download_all(render["id"], "relit/", kind="video")
"""

from service.client.bars import JobBars
from service.client.http import ApiError, Event
from service.client.jobs import Jobs
from service.client.uploads import Uploads, manifest_of

__all__ = ["ApiError", "Client", "Event", "JobBars", "manifest_of"]


class Client(Uploads, Jobs):
    """The API at `base_url`, with a bearer key (None when the server has no keys); see
    `service.client.http.Http` for the connection's options."""
