"""The Zentrix HX-6: a CANopen hexapod controller written from CiA 301 alone (MANUAL.md, zentrix_hx6.eds)."""
