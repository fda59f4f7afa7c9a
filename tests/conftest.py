"""Settings shared by every test folder.

Hypothesis: the data generation of the property tests is timed by hypothesis's health check;
on the shared 2-core CI machine, under load, generating a case can take longer than that check
allows, which says nothing about the code under test. The check is turned off for speed only;
every other health check, and every example count, stays as each test sets it.
"""

from hypothesis import HealthCheck, settings

settings.register_profile("pregrasp", suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("pregrasp")
