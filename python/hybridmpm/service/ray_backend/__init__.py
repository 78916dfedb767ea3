"""The Ray backend of the service (``hybridmpm serve --backend ray``): each
session's :class:`~hybridmpm.service.core.SessionCore` runs in a Ray actor
(:mod:`.actor`), a registry actor counts the cluster's sessions and holds
its store (:mod:`.registry`; the real-time sessions' shares of their
nodes in :mod:`.shares`), and any number of front ends reach them
through :class:`~hybridmpm.service.ray_backend.manager.RaySessionManager`
(:mod:`.manager`; its handles, connection and error translation in
:mod:`.front`), which implements :class:`~hybridmpm.service.backend.SessionBackend`
beside the local backend.

Importing this package needs Ray (the ``cluster`` extra); the local backend
never imports it.
"""
