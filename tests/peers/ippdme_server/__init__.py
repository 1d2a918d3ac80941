"""An I++ DME 1.4.3 server written from the specification and NIST's test files alone (NOTES.md)."""
