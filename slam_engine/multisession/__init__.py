"""Maps that outlive a drive: localise a new drive in a saved map (``localization``), and extend a map
with a new drive or merge two maps into one optimised pose graph (``joining``)."""
