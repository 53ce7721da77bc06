"""``mcrs-campaign``: the section-6 matrix run on one machine, interruptible, with committed records."""
