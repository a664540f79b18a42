"""Camera ego-motion from events: angular velocity by contrast maximisation, integrated to orientation."""
