"""Conformance to I++ DME 1.4.3: NIST's test files, validators that mirror NIST's parsers, and the tests using them."""
