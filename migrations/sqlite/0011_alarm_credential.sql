-- Spoofwatch schema, version 11: the credential behind each alarm (docs/detector.md §11).
--
-- `credential` names the credential whose call sent the samples that raised the alarm, never its
-- secret: `certificate <name> sha256:<digest prefix>`, `token <name> sha256:<digest prefix>`,
-- `admin token`, or `unauthenticated` on a server without identities. NULL on alarms stored before
-- this version. `credential_per_vehicle` says that each vehicle of that credential is its own
-- source of evidence for area incidents (a gateway whose roles-file entry says it forwards
-- independent receivers, or a server without identities); otherwise all the credential's vehicles
-- are one source.
ALTER TABLE alarm_events ADD COLUMN credential TEXT;
ALTER TABLE alarm_events ADD COLUMN credential_per_vehicle BOOLEAN NOT NULL DEFAULT FALSE;
