"""The `renderer` command (`main`), `renderer animate` (`animate`) and the renders that run outside this
process (`backends`: Mitsuba, Ray clusters)."""
