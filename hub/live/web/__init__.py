"""The fleet health dashboard: one web page (shipped in `static/`, nothing from a CDN), its JSON
API and login, a live WebSocket, and Prometheus ``/metrics``, served by the hub service
`fleetdaq.hub.live.web.service.WebService` on ``hub.dashboard.listen``.

Modules: `service` (the thread, loop and lifecycle), `api` (HTTP routes and middlewares),
`live` (the WebSocket), `auth` (logins, sessions, CSRF), `users` (the users file), `events`
(the event tail), `parts` (what it needs from the hub), `stats` (its counters).
"""
