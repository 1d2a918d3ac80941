"""The coverage study's parts: recordings as another simulator makes them (``readings``) and the method doc's
figures (``method_doc``)."""
