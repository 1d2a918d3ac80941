"""The operator panel in headless Chromium: a whole run, live views, the adaptive card and drift."""
