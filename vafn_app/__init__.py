"""vafn_app: applications that wire the layers together (``vafn-demo``); it may import every vafn package."""
