"""The browser viewer: a static page plus server-side deferred renders over WebSocket.

Depends on ``core`` only; the API supplies job lookups through :class:`JobView`
callbacks and mounts the routes with :func:`mount`.
"""

from viewer_web.routes import mount
from viewer_web.service import JobView, ViewerService

__all__ = ["JobView", "ViewerService", "mount"]
