-- Spoofwatch schema, version 12: incidents ended by hand (EndIncident), audited with the incident.
--
-- `closed_as` is 'ended' (the threat is over) or 'dismissed' (it was never real); `closed_reason` is
-- the admin's reason and `closed_by` the credential of the call (a label such as `token <name>
-- sha256:<digest prefix>`, never a secret). The time is the row's `ended_at`. All three are NULL for
-- an incident that is open or ended on its own. Once set they are never rewritten, and the
-- correlator writes no more changes to such an incident.
ALTER TABLE incidents ADD COLUMN closed_as TEXT CHECK (closed_as IN ('ended', 'dismissed'));
ALTER TABLE incidents ADD COLUMN closed_reason TEXT;
ALTER TABLE incidents ADD COLUMN closed_by TEXT;
