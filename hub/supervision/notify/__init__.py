"""E-mail notifications of alarm transitions
(`fleetdaq.hub.supervision.notify.service.EmailNotifier`).

One concern per module: `policy` (who gets what, when: groups, digests, snooze, rate limits;
pure, no I/O), `compose` (the mails, plain text + HTML), `held` (transitions waiting for a
digest, kept on disk), `outbox` (one file per mail until the server took it), `transport` (one
SMTP session: TLS, AUTH, what a reply means), `delivery` (the sender thread: retries with
backoff), `credentials` (the SMTP password, from the environment or a file), `clock` (time,
injectable) and `service` (the hub service that ties them together).
"""
